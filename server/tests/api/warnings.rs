//! Log volume: a client that makes every update
//! non-finite gets one warning per period, not one per report.

use std::io::Write;
use std::sync::{Arc, Mutex};

use esa_server::pb;
use esa_server::EsaServer;

/// Log output collected in memory.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[test]
fn non_finite_updates_are_warned_about_once_per_period() {
    let captured = Captured::default();
    let writer = captured.clone();
    let subscriber = tracing_subscriber::fmt()
        .with_writer(move || writer.clone())
        .with_ansi(false)
        .finish();
    let handler = EsaServer::builder().build().handler();
    let reports = 10_000;
    tracing::subscriber::with_default(subscriber, || {
        // alpha * s * Q overflows to infinity from step 1 on (s = 0 at step 0).
        let config = pb::SessionConfig {
            action_dim: 1,
            dt: 0.01,
            amplitude: vec![1.0],
            frequency: vec![60.0],
            learning_rate: vec![1e308],
            disable_highpass: true,
            ..Default::default()
        };
        handler
            .create_session(pb::CreateSessionRequest {
                session_id: "loud".into(),
                config: Some(config),
                progress: None,
            })
            .unwrap();
        for step in 0..reports {
            handler
                .probe(pb::ProbeRequest {
                    session_id: "loud".into(),
                    step,
                    action: vec![0.0],
                    ..Default::default()
                })
                .unwrap();
            handler
                .report(pb::ReportRequest {
                    session_id: "loud".into(),
                    step,
                    q_value: 1e308,
                    ..Default::default()
                })
                .unwrap();
        }
    });
    let log = String::from_utf8(captured.0.lock().unwrap().clone()).unwrap();
    let warnings: Vec<&str> = log.lines().filter(|l| l.contains("non-finite")).collect();
    assert_eq!(warnings.len(), 1, "{log}");
    assert!(
        warnings[0].contains("WARN") && warnings[0].contains("loud"),
        "{log}"
    );
    let metrics = handler.render_metrics();
    let skipped = format!("esa_nonfinite_updates_skipped_total {}\n", reports - 1);
    assert!(metrics.contains(&skipped), "{metrics}");
}
