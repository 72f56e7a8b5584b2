//! The opt-in HTTP endpoint (`--metrics-listen`): `GET /metrics` answers the
//! handler's [`crate::metrics::Metrics`] in the OpenMetrics text format
//! (which Prometheus scrapes natively). Like the transports, it only reads through [`EsaHandler`].

use std::sync::Arc;

use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;

use crate::handler::EsaHandler;

/// Serves `GET /metrics` on `listener` until the task is dropped.
pub async fn serve_metrics(
    listener: tokio::net::TcpListener,
    handler: Arc<EsaHandler>,
) -> std::io::Result<()> {
    let app = Router::new()
        .route("/metrics", get(metrics_page))
        .with_state(handler);
    axum::serve(listener, app).await
}

async fn metrics_page(State(handler): State<Arc<EsaHandler>>) -> impl IntoResponse {
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        handler.render_metrics(),
    )
}
