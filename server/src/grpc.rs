//! The gRPC service: a thin adapter from tonic to [`EsaHandler`].

use std::pin::Pin;
use std::sync::Arc;

use futures_util::stream::{self, Stream, StreamExt};
use tokio::sync::watch;
use tonic::{Request, Response, Status, Streaming};

use crate::error::{status, Error};
use crate::handler::EsaHandler;
use crate::pb;
use crate::pb::esa_service_server::EsaService;

/// `esa.v1.EsaService` over gRPC.
pub struct GrpcService {
    handler: Arc<EsaHandler>,
    stop: watch::Receiver<bool>,
}

impl GrpcService {
    /// The service over `handler`; open StepStreams end once `stop` turns true.
    pub fn new(handler: Arc<EsaHandler>, stop: watch::Receiver<bool>) -> Self {
        Self { handler, stop }
    }
}

/// Completes once `stop` turns true (or its sender is gone).
pub(crate) async fn stopped(mut stop: watch::Receiver<bool>) {
    // Err means the sender is gone: the server has stopped either way.
    let _ = stop.wait_for(|stop| *stop).await;
}

fn respond<T>(result: Result<T, Error>) -> Result<Response<T>, Status> {
    result.map(Response::new).map_err(status)
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<pb::StepStreamResponse, Status>> + Send>>;

#[tonic::async_trait]
impl EsaService for GrpcService {
    async fn create_session(
        &self,
        request: Request<pb::CreateSessionRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        respond(self.handler.create_session(request.into_inner()))
    }

    async fn probe(
        &self,
        request: Request<pb::ProbeRequest>,
    ) -> Result<Response<pb::ProbeResponse>, Status> {
        respond(self.handler.probe(request.into_inner()))
    }

    async fn report(
        &self,
        request: Request<pb::ReportRequest>,
    ) -> Result<Response<pb::ReportResponse>, Status> {
        respond(self.handler.report(request.into_inner()))
    }

    async fn end_episode(
        &self,
        request: Request<pb::EndEpisodeRequest>,
    ) -> Result<Response<pb::EndEpisodeResponse>, Status> {
        respond(self.handler.end_episode(request.into_inner()))
    }

    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        respond(self.handler.close_session(request.into_inner()))
    }

    async fn get_session(
        &self,
        request: Request<pb::GetSessionRequest>,
    ) -> Result<Response<pb::GetSessionResponse>, Status> {
        respond(self.handler.get_session(request.into_inner()))
    }

    async fn probe_batch(
        &self,
        request: Request<pb::ProbeBatchRequest>,
    ) -> Result<Response<pb::ProbeBatchResponse>, Status> {
        respond(self.handler.probe_batch(request.into_inner()))
    }

    async fn report_batch(
        &self,
        request: Request<pb::ReportBatchRequest>,
    ) -> Result<Response<pb::ReportBatchResponse>, Status> {
        respond(self.handler.report_batch(request.into_inner()))
    }

    type StepStreamStream = ResponseStream;

    /// Answers each message as it arrives, in order, without a relay task or
    /// channel: the response stream is the request stream mapped through the
    /// handler. A transport error from the client ends the stream; server
    /// shutdown ends it with UNAVAILABLE so the client knows to reconnect.
    async fn step_stream(
        &self,
        request: Request<Streaming<pb::StepStreamRequest>>,
    ) -> Result<Response<ResponseStream>, Status> {
        let handler = Arc::clone(&self.handler);
        let stop = self.stop.clone();
        let responses = request
            .into_inner()
            .map(move |message| message.map(|req| handler.step(req)))
            .take_until(stopped(self.stop.clone()))
            .chain(
                stream::once(async move {
                    stop.borrow()
                        .then(|| Err(Status::unavailable("the server is shutting down")))
                })
                .filter_map(std::future::ready),
            );
        Ok(Response::new(Box::pin(responses)))
    }
}
