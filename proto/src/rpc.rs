//! The RPCs of `esa.v1.EsaService`, as one enum for metrics labels and for
//! transports that route by RPC name (e.g. Zenoh key `esa/v1/<RpcName>`).

/// One RPC of `esa.v1.EsaService`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Rpc {
    CreateSession,
    Probe,
    Report,
    EndEpisode,
    CloseSession,
    GetSession,
    ProbeBatch,
    ReportBatch,
    StepStream,
}

impl Rpc {
    /// Every RPC, in proto order.
    pub const ALL: [Rpc; 9] = [
        Rpc::CreateSession,
        Rpc::Probe,
        Rpc::Report,
        Rpc::EndEpisode,
        Rpc::CloseSession,
        Rpc::GetSession,
        Rpc::ProbeBatch,
        Rpc::ReportBatch,
        Rpc::StepStream,
    ];

    /// The method name as written in the proto (`"ProbeBatch"`).
    pub fn name(self) -> &'static str {
        match self {
            Rpc::CreateSession => "CreateSession",
            Rpc::Probe => "Probe",
            Rpc::Report => "Report",
            Rpc::EndEpisode => "EndEpisode",
            Rpc::CloseSession => "CloseSession",
            Rpc::GetSession => "GetSession",
            Rpc::ProbeBatch => "ProbeBatch",
            Rpc::ReportBatch => "ReportBatch",
            Rpc::StepStream => "StepStream",
        }
    }
}
