//! The one error type of the load generator.

/// Anything that stops a benchmark run.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The esa-server child process could not be started or stopped.
    #[error("esa-server process: {0}")]
    Server(String),
    /// Local I/O (spawning, /proc, writing the JSON).
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
    /// Connecting to the server failed.
    #[error("connect: {0}")]
    Connect(#[from] tonic::transport::Error),
    /// A gRPC call failed.
    #[error("rpc failed: {0}")]
    Rpc(#[from] tonic::Status),
    /// A StepStream message was answered with an in-band error, or a Zenoh
    /// query with a reply error (both carry a `StreamError`).
    #[error("server error (gRPC code {code}): {message}")]
    Stream {
        /// The gRPC status code number.
        code: i32,
        /// The server's message.
        message: String,
    },
    /// The Zenoh session or one of its queries failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The server answered with something the contract does not allow.
    #[error("unexpected response: {0}")]
    Protocol(String),
    /// A latency could not be recorded.
    #[error("histogram: {0}")]
    Histogram(#[from] hdrhistogram::RecordError),
    /// Encoding the results failed.
    #[error("json: {0}")]
    Json(#[from] serde_json::Error),
}

/// Result with the load generator's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
