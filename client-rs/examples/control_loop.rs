//! A small Rust control loop with ESA: 4 copies of a 1-D task whose best action is 0.7, a
//! policy that always says 0.0, and a critic `Q(a) = -(a - 0.7)^2`. ESA moves the applied
//! action `a_t + v(t)` toward the critic's maximum, one pipelined StepStream round trip per
//! step (the report rides with the next probe).
//!
//! ```bash
//! cargo run -p esa-client --example control_loop            # spawns target/release/esa-server
//! cargo run -p esa-client --example control_loop -- 127.0.0.1:50051   # or uses a running one
//! ```
//!
//! The server binary: `ESA_SERVER_BIN`, else the workspace's `target/release/esa-server`
//! (`cargo build --release -p esa-server`), else `target/debug/esa-server`.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

use esa_client::{pb, Client, Options};

const ENVS: usize = 4;
const BEST: f64 = 0.7;

/// The critic of the toy task.
fn critic(action: f64) -> f64 {
    -(action - BEST) * (action - BEST)
}

/// An `esa-server` child on a free TCP port, stopped when dropped.
pub struct Server {
    child: Child,
    /// `127.0.0.1:<port>`.
    pub address: String,
}

impl Server {
    /// Starts the server binary `ESA_SERVER_BIN` names, or the workspace's build.
    pub fn spawn() -> Result<Self, String> {
        Self::spawn_with(&[])
    }

    /// The same with more server flags (`--auth-token-file`, `--tls-cert`, ...).
    pub fn spawn_with(flags: &[&str]) -> Result<Self, String> {
        let binary = server_binary().ok_or(
            "no esa-server: set ESA_SERVER_BIN or run `cargo build --release -p esa-server`",
        )?;
        let mut child = Command::new(&binary)
            .args(["--listen", "127.0.0.1:0", "--parent-pid"])
            .arg(std::process::id().to_string())
            .args(flags)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|err| format!("{}: {err}", binary.display()))?;
        let stdout = child.stdout.take().ok_or("no stdout")?;
        let mut lines = BufReader::new(stdout).lines();
        let address = loop {
            match lines.next() {
                Some(Ok(line)) => {
                    if let Some(address) = line.strip_prefix("listening on ") {
                        break address.trim().to_string();
                    }
                }
                _ => {
                    let _ = child.kill();
                    return Err(format!("{} exited before listening", binary.display()));
                }
            }
        };
        Ok(Self { child, address })
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `ESA_SERVER_BIN`, else the workspace target directory's release or debug build.
pub fn server_binary() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("ESA_SERVER_BIN") {
        return Some(PathBuf::from(path));
    }
    let target = std::env::var_os("CARGO_TARGET_DIR").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target"),
        PathBuf::from,
    );
    ["release", "debug"]
        .iter()
        .map(|profile| target.join(profile).join("esa-server"))
        .find(|path| path.is_file())
}

/// Runs `steps` steps of `ENVS` envs against the server at `address`; returns the mean action
/// the envs executed over the last 20 steps.
pub async fn run(address: &str, steps: usize) -> Result<f64, esa_client::Error> {
    let client = Client::connect(address, Options::default()).await?;
    let config = pb::SessionConfig {
        action_dim: 1,
        dt: 0.04,
        amplitude: vec![0.2],
        frequency: vec![31.4],
        learning_rate: vec![0.5],
        action_low: vec![-1.0],
        action_high: vec![1.0],
        ..Default::default()
    };
    let mut batch = client.create_batch(config, ENVS, true).await?;
    let policy = vec![0.0; ENVS];
    let mut recent = Vec::new();
    for t in 0..steps {
        let starts = vec![t == 0; ENVS];
        let (probes, applied) = batch.probe(&policy, &starts, None).await?;
        let q: Vec<f64> = probes.iter().copied().map(critic).collect();
        // Deferred: sent now, answered together with the next probe.
        batch.report(&q, None, true).await?;
        if t + 20 >= steps {
            recent.extend(applied);
        }
    }
    batch.close().await?;
    Ok(recent.iter().sum::<f64>() / recent.len() as f64)
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let (_server, address) = match std::env::args().nth(1) {
        Some(address) => (None, address),
        None => {
            let server = Server::spawn()?;
            let address = server.address.clone();
            (Some(server), address)
        }
    };
    let mean = run(&address, 300).await?;
    println!(
        "policy says 0.0, the critic's best is {BEST}; ESA executed {mean:.3} on average over \
         the last 20 steps of {ENVS} envs"
    );
    Ok(())
}
