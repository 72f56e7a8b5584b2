//! Resident memory per session: a fresh server's VmRSS before and after
//! creating many sessions, and after stepping each of them once.

use serde::Serialize;

use crate::driver::{connect, create_sessions, Api, Stepper};
use crate::error::{Error, Result};
use crate::server_process::{ServerProcess, Socket};

/// Sessions stepped per ProbeBatch/ReportBatch when touching all of them.
const STEP_CHUNK: usize = 1024;

/// VmRSS readings of one server around creating `sessions` sessions.
#[derive(Clone, Debug, Serialize)]
pub struct Rss {
    /// Sessions created.
    pub sessions: usize,
    /// Action dimension of each.
    pub dim: usize,
    /// VmRSS after one session was created and closed (connections warm).
    pub before_kib: u64,
    /// VmRSS with all sessions created and idle.
    pub idle_kib: u64,
    /// VmRSS after one probe + report on every session.
    pub stepped_kib: u64,
    /// `(idle - before) / sessions`, bytes.
    pub idle_bytes_per_session: f64,
    /// `(stepped - before) / sessions`, bytes.
    pub stepped_bytes_per_session: f64,
}

/// Starts its own server and measures how its RSS grows with `sessions`
/// sessions of dimension `dim`, created by `concurrency` clients at once.
pub async fn rss_per_session(
    binary: &std::path::Path,
    sessions: usize,
    dim: usize,
    concurrency: usize,
) -> Result<Rss> {
    let server = ServerProcess::start(binary, Socket::Tcp, sessions + 1)?;
    let address = server.address().clone();
    let mut warm = connect(&address).await?;
    let ids = create_sessions(&mut warm, "rss-warm", 1, dim).await?;
    crate::driver::close_sessions(&mut warm, &ids).await?;
    let before_kib = server.rss_kib()?;

    let per_client = sessions.div_ceil(concurrency.max(1));
    let tasks: Vec<_> = (0..concurrency.max(1))
        .map(|client| {
            let address = address.clone();
            let n = per_client.min(sessions.saturating_sub(client * per_client));
            // As long as the Python client's ids (`<uuid>-<i>`): the id is stored too.
            let name = format!("rss-{client}");
            let prefix = format!("{name:0>36}");
            tokio::spawn(async move {
                let mut connection = connect(&address).await?;
                create_sessions(&mut connection, &prefix, n, dim).await
            })
        })
        .collect();
    let mut ids = Vec::with_capacity(sessions);
    for task in tasks {
        ids.extend(
            task.await
                .map_err(|err| Error::Protocol(format!("client task failed: {err}")))??,
        );
    }
    let idle_kib = server.rss_kib()?;

    for chunk in ids.chunks(STEP_CHUNK) {
        let mut stepper = Stepper::new(warm.clone(), Api::Batch, chunk.to_vec(), dim).await?;
        stepper.pair().await?;
    }
    let stepped_kib = server.rss_kib()?;

    let per_session = |kib: u64| kib.saturating_sub(before_kib) as f64 * 1024.0 / sessions as f64;
    Ok(Rss {
        sessions,
        dim,
        before_kib,
        idle_kib,
        stepped_kib,
        idle_bytes_per_session: per_session(idle_kib),
        stepped_bytes_per_session: per_session(stepped_kib),
    })
}
