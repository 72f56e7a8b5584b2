//! Transport-independent request handling: one method per RPC, taking the
//! prost request and returning the prost response or an [`Error`]. The gRPC
//! service is a thin adapter over it, and so is any other transport (such as
//! Zenoh), so every transport behaves identically. Share it as
//! `Arc<EsaHandler>`; all methods take `&self`.

use std::sync::Arc;
use std::time::Instant;

use esa_core::batch;
use esa_core::fused_step::{self, CriticValues, LinearCritic, StepCritic};
use esa_store::unary;
use prost::Message;
use subtle::ConstantTimeEq as _;

use crate::codec::{self, WireLimits};
use crate::convert::{config_from_proto, session_snapshot};
use crate::error::{grpc_code, stream_error, Error};
use crate::metrics::{Metrics, StoreGauges};
use crate::pb;
use crate::pb::step_stream_request::Kind as StreamRequest;
use crate::pb::step_stream_response::Kind as StreamResponse;
use crate::store::SessionStore;
use crate::throttle::{Throttle, WARNING_PERIOD};
use esa_proto::convert::{batch_progress, new_session};
use esa_proto::Rpc;

/// Handles the RPCs of `esa.v1.EsaService` against one session store.
pub struct EsaHandler {
    store: SessionStore,
    metrics: Arc<Metrics>,
    token: Option<Box<[u8]>>,
    nonfinite_warnings: Throttle,
}

impl EsaHandler {
    /// A handler serving the sessions of `store` to anyone who can reach it.
    pub fn new(store: SessionStore) -> Self {
        Self {
            store,
            metrics: Arc::default(),
            token: None,
            nonfinite_warnings: Throttle::new(WARNING_PERIOD),
        }
    }

    /// Requires every request to present `token` (see [`EsaHandler::authorize`]).
    pub fn with_auth_token(mut self, token: impl Into<Box<[u8]>>) -> Self {
        self.token = Some(token.into());
        self
    }

    /// Checks the token a request presented: Ok when the server requires none or `presented`
    /// equals it (compared in constant time), else UNAUTHENTICATED. Transports call it before
    /// handling a request: gRPC with the `authorization: Bearer <token>` header, Zenoh with the
    /// query's attachment.
    pub fn authorize(&self, presented: Option<&[u8]>) -> Result<(), Error> {
        let Some(token) = &self.token else {
            return Ok(());
        };
        match presented {
            Some(presented) if bool::from(presented.ct_eq(token)) => Ok(()),
            Some(_) => Err(Error::Unauthenticated(
                "the auth token does not match the server's (--auth-token-file)".into(),
            )),
            None => Err(Error::Unauthenticated(
                "this server requires an auth token (--auth-token-file): send it as \
                 `authorization: Bearer <token>` metadata over gRPC, or as the query \
                 attachment over Zenoh"
                    .into(),
            )),
        }
    }

    /// The session store (for the sweeper and for inspection).
    pub fn store(&self) -> &SessionStore {
        &self.store
    }

    /// The counters that transports add to (connections).
    pub fn metrics(&self) -> Arc<Metrics> {
        Arc::clone(&self.metrics)
    }

    /// The Prometheus text exposition of this handler's metrics.
    pub fn render_metrics(&self) -> String {
        self.metrics.render(&StoreGauges {
            sessions_live: self.store.live(),
            sessions_expired: self.store.expired_total(),
            session_memory_bytes: self.store.memory(),
        })
    }

    /// Logs what throttled warnings held back, once their period has passed (called
    /// periodically by the server).
    pub fn log_suppressed_warnings(&self) {
        if let Some(skipped) = self.nonfinite_warnings.summary() {
            tracing::warn!(
                skipped,
                period = ?WARNING_PERIOD,
                "more shift updates would have been non-finite and were skipped since the last \
                 warning (esa_nonfinite_updates_skipped_total counts them all)"
            );
        }
    }

    /// Creates a session (a UUID id when none is given), or returns the
    /// existing one for the same id and an identical config.
    pub fn create_session(
        &self,
        req: pb::CreateSessionRequest,
    ) -> Result<pb::CreateSessionResponse, Error> {
        self.observe(Rpc::CreateSession, || {
            let session = new_session(config_from_proto(req.config)?, req.progress)?;
            let session_id = self.store.create(req.session_id, session)?;
            Ok(pb::CreateSessionResponse { session_id })
        })
    }

    /// Probes one session at its current step.
    pub fn probe(&self, req: pb::ProbeRequest) -> Result<pb::ProbeResponse, Error> {
        self.observe(Rpc::Probe, || {
            self.store.with_session(&req.session_id, |session| {
                let probed = unary::probe(
                    session,
                    req.step,
                    &req.action,
                    &req.action_scale,
                    req.episode_start,
                )?;
                Ok(pb::ProbeResponse {
                    probe: probed.probe,
                    step: req.step,
                    action: probed.applied,
                })
            })
        })
    }

    /// Reports Q for one session's pending probe (or replays the last report).
    pub fn report(&self, req: pb::ReportRequest) -> Result<pb::ReportResponse, Error> {
        self.observe(Rpc::Report, || {
            self.store.with_session(&req.session_id, |session| {
                let reported = unary::report(session, req.step, req.q_value, req.q_reference)?;
                self.note_nonfinite(reported.outcome.nonfinite_skipped, &req.session_id);
                Ok(pb::ReportResponse {
                    action: reported.action,
                    step: req.step,
                })
            })
        })
    }

    /// Ends one session's episode.
    pub fn end_episode(&self, req: pb::EndEpisodeRequest) -> Result<pb::EndEpisodeResponse, Error> {
        self.observe(Rpc::EndEpisode, || {
            self.store.with_session(&req.session_id, |session| {
                Ok(pb::EndEpisodeResponse {
                    episodes_completed: session.end_episode(),
                })
            })
        })
    }

    /// Closes a session; its id is NOT_FOUND afterwards.
    pub fn close_session(
        &self,
        req: pb::CloseSessionRequest,
    ) -> Result<pb::CloseSessionResponse, Error> {
        self.observe(Rpc::CloseSession, || {
            self.store.close(&req.session_id)?;
            Ok(pb::CloseSessionResponse {})
        })
    }

    /// A snapshot of one session's config and state.
    pub fn get_session(&self, req: pb::GetSessionRequest) -> Result<pb::GetSessionResponse, Error> {
        self.observe(Rpc::GetSession, || {
            self.store
                .with_session(&req.session_id, |session| Ok(session_snapshot(session)))
        })
    }

    /// Probes N sessions at once; all-or-nothing.
    pub fn probe_batch(&self, req: pb::ProbeBatchRequest) -> Result<pb::ProbeBatchResponse, Error> {
        self.observe(Rpc::ProbeBatch, || self.run_probe_batch(req))
    }

    /// Reports to N sessions at once; all-or-nothing.
    pub fn report_batch(
        &self,
        req: pb::ReportBatchRequest,
    ) -> Result<pb::ReportBatchResponse, Error> {
        self.observe(Rpc::ReportBatch, || self.run_report_batch(req))
    }

    /// Answers one StepStream message; a failure becomes an in-band
    /// `StreamError` so the stream can go on.
    pub fn step(&self, req: pb::StepStreamRequest) -> pb::StepStreamResponse {
        let result = self.observe(Rpc::StepStream, || match req.kind {
            Some(StreamRequest::ProbeBatch(batch)) => {
                self.run_probe_batch(batch).map(StreamResponse::ProbeBatch)
            }
            Some(StreamRequest::ReportBatch(batch)) => self
                .run_report_batch(batch)
                .map(StreamResponse::ReportBatch),
            Some(StreamRequest::StepLinearBatch(batch)) => {
                let critic = LinearCritic {
                    gains: &batch.critic_gains,
                    offsets: &batch.critic_offsets,
                    paired: batch.paired,
                };
                self.run_fused_step(batch.probe.as_ref(), &critic)
                    .map(StreamResponse::StepLinearBatch)
            }
            Some(StreamRequest::StepBatch(batch)) => {
                let values = CriticValues {
                    q_values: &batch.q_values,
                    q_references: &batch.q_references,
                };
                self.run_fused_step(batch.probe.as_ref(), &values)
                    .map(StreamResponse::StepBatch)
            }
            None => Err(Error::InvalidArgument(
                "kind: expected probe_batch, report_batch, step_linear_batch or step_batch, \
                 got none"
                    .into(),
            )),
        });
        pb::StepStreamResponse {
            kind: Some(result.unwrap_or_else(|err| StreamResponse::Error(stream_error(err)))),
        }
    }

    /// Decodes `payload` as the request of `rpc`, handles it and returns the
    /// encoded response: the entry point for message-based transports. For
    /// [`Rpc::StepStream`] the payload is one `StepStreamRequest` and errors
    /// come back in-band, as on the gRPC stream.
    pub fn handle_encoded(&self, rpc: Rpc, payload: &[u8]) -> Result<Vec<u8>, Error> {
        match rpc {
            Rpc::CreateSession => encoded(payload, |r| self.create_session(r)),
            Rpc::Probe => encoded(payload, |r| self.probe(r)),
            Rpc::Report => encoded(payload, |r| self.report(r)),
            Rpc::EndEpisode => encoded(payload, |r| self.end_episode(r)),
            Rpc::CloseSession => encoded(payload, |r| self.close_session(r)),
            Rpc::GetSession => encoded(payload, |r| self.get_session(r)),
            Rpc::ProbeBatch => encoded(payload, |r| self.probe_batch(r)),
            Rpc::ReportBatch => encoded(payload, |r| self.report_batch(r)),
            Rpc::StepStream => encoded(payload, |r| Ok(self.step(r))),
        }
    }

    fn run_probe_batch(&self, req: pb::ProbeBatchRequest) -> Result<pb::ProbeBatchResponse, Error> {
        // The lengths first: a malformed request is refused before any session is looked up.
        batch::check_probe_lengths(
            req.session_ids.len(),
            req.steps.len(),
            req.episode_starts.len(),
        )?;
        self.store.with_batch(&req.session_ids, |sessions| {
            let (mut probes, mut actions) = (Vec::new(), Vec::new());
            batch::probe(
                sessions,
                &req.steps,
                &req.actions,
                &req.episode_starts,
                &req.action_scales,
                &mut probes,
                &mut actions,
            )?;
            let (episodes_completed, response_mean_squares) = batch_progress(sessions);
            Ok(pb::ProbeBatchResponse {
                probes,
                actions,
                episodes_completed,
                response_mean_squares,
            })
        })
    }

    fn run_report_batch(
        &self,
        req: pb::ReportBatchRequest,
    ) -> Result<pb::ReportBatchResponse, Error> {
        batch::check_report_lengths(
            req.session_ids.len(),
            req.steps.len(),
            req.q_values.len(),
            req.q_references.len(),
        )?;
        self.store.with_batch(&req.session_ids, |sessions| {
            let mut actions = Vec::new();
            batch::report(
                sessions,
                &req.steps,
                &req.q_values,
                &req.q_references,
                &mut actions,
                |index, outcome| {
                    let id = req.session_ids.get(index).map_or("", String::as_str);
                    self.note_nonfinite(outcome.nonfinite_skipped, id);
                },
            )?;
            Ok(pb::ReportBatchResponse { actions })
        })
    }

    /// A StepStream fused step (`step_linear_batch`, `step_batch`): `probe` with `critic`'s
    /// report, answered with the probes, the applied actions and the shifts `v(t + 1)`.
    fn run_fused_step(
        &self,
        probe: Option<&pb::ProbeBatchRequest>,
        critic: &impl StepCritic,
    ) -> Result<pb::StepBatchResponse, Error> {
        let probe = probe.ok_or_else(|| {
            Error::InvalidArgument("probe: expected the step's probe batch, got none".into())
        })?;
        batch::check_probe_lengths(
            probe.session_ids.len(),
            probe.steps.len(),
            probe.episode_starts.len(),
        )?;
        self.store.with_batch(&probe.session_ids, |sessions| {
            let (mut probes, mut actions) = (Vec::new(), Vec::new());
            fused_step::step(
                sessions,
                &probe.steps,
                &probe.actions,
                &probe.episode_starts,
                &probe.action_scales,
                critic,
                &mut probes,
                &mut actions,
                |index, outcome| {
                    let id = probe.session_ids.get(index).map_or("", String::as_str);
                    self.note_nonfinite(outcome.nonfinite_skipped, id);
                },
            )?;
            let shifts = sessions
                .iter()
                .flat_map(|session| session.shift().iter().copied())
                .collect();
            let (episodes_completed, response_mean_squares) = batch_progress(sessions);
            Ok(pb::StepBatchResponse {
                probes,
                actions,
                shifts,
                episodes_completed,
                response_mean_squares,
            })
        })
    }

    /// Runs `f` as one request of `rpc`, recording its code and latency.
    fn observe<T>(&self, rpc: Rpc, f: impl FnOnce() -> Result<T, Error>) -> Result<T, Error> {
        let start = Instant::now();
        let result = f();
        let code = match &result {
            Ok(_) => tonic::Code::Ok,
            Err(err) => {
                let code = grpc_code(err);
                tracing::debug!(rpc = rpc.name(), ?code, %err, "request failed");
                code
            }
        };
        self.metrics.observe(rpc, code, start.elapsed());
        result
    }

    fn note_nonfinite(&self, skipped: bool, session_id: &str) {
        if !skipped {
            return;
        }
        self.metrics.add_nonfinite_skipped(1);
        // One client can make every report non-finite: log once per period, count the rest.
        if let Some(suppressed) = self.nonfinite_warnings.admit() {
            tracing::warn!(
                session_id,
                suppressed,
                period = ?WARNING_PERIOD,
                "shift update would be non-finite; kept the previous shift (this warning is \
                 logged at most once per period, with the number suppressed since the last)"
            );
        }
    }
}

fn encoded<Req: Message + Default + WireLimits, Resp: Message>(
    payload: &[u8],
    handle: impl FnOnce(Req) -> Result<Resp, Error>,
) -> Result<Vec<u8>, Error> {
    handle(codec::decode(payload)?).map(|resp| resp.encode_to_vec())
}
