//! TLS on the gRPC listener: clients that trust the server's CA are served;
//! plaintext clients, clients that trust another CA and, with a client CA,
//! clients without a certificate from it are not; unusable certificate files
//! stop the executable before it listens. Certificates are made per run.

use std::io::Read as _;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use esa_server::pb;
use esa_server::pb::esa_service_client::EsaServiceClient;
use esa_server::{EsaServer, TlsSettings};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose, IsCa,
    KeyPair, KeyUsagePurpose,
};
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Identity};

use crate::common::{config, launch, read_line_after, start_with, BIN};
use crate::stream::Stream;

/// Long enough for a loopback handshake on a loaded machine, short enough to fail fast.
const CONNECT: Duration = Duration::from_secs(10);

/// A certificate authority made for one test.
pub(crate) struct Pki {
    ca: CertifiedIssuer<'static, KeyPair>,
}

/// A certificate (PEM) and its private key (PEM, PKCS#8).
pub(crate) struct Leaf {
    pub(crate) cert: String,
    pub(crate) key: String,
}

impl Pki {
    pub(crate) fn new(name: &str) -> Self {
        let mut params = CertificateParams::new(Vec::<String>::new()).expect("CA params");
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        params.distinguished_name.push(DnType::CommonName, name);
        let key = KeyPair::generate().expect("CA key");
        Self {
            ca: CertifiedIssuer::self_signed(params, key).expect("CA certificate"),
        }
    }

    pub(crate) fn ca_pem(&self) -> String {
        self.ca.pem()
    }

    /// A certificate for `localhost` and 127.0.0.1, good for a server and a client alike.
    pub(crate) fn leaf(&self, name: &str) -> Leaf {
        let mut params = CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()])
            .expect("leaf params");
        params.distinguished_name.push(DnType::CommonName, name);
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.use_authority_key_identifier_extension = true;
        let key = KeyPair::generate().expect("leaf key");
        let cert = params.signed_by(&key, &self.ca).expect("leaf certificate");
        Leaf {
            cert: cert.pem(),
            key: key.serialize_pem(),
        }
    }
}

/// A TLS client of `addr` trusting `ca`, presenting `identity` if given; Err when the
/// connection (or its TLS handshake) fails.
async fn tls_client(
    addr: SocketAddr,
    ca: &str,
    identity: Option<&Leaf>,
) -> Result<EsaServiceClient<Channel>, String> {
    let mut tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(ca))
        .domain_name("localhost");
    if let Some(leaf) = identity {
        tls = tls.identity(Identity::from_pem(&leaf.cert, &leaf.key));
    }
    let endpoint = Channel::from_shared(format!("https://{addr}"))
        .expect("uri")
        .tls_config(tls)
        .expect("client TLS config")
        .connect_timeout(CONNECT)
        .timeout(CONNECT);
    let channel = endpoint.connect().await.map_err(|err| format!("{err:?}"))?;
    Ok(EsaServiceClient::new(channel))
}

async fn plaintext_client(addr: SocketAddr) -> Result<EsaServiceClient<Channel>, String> {
    let endpoint = Channel::from_shared(format!("http://{addr}"))
        .expect("uri")
        .connect_timeout(CONNECT)
        .timeout(CONNECT);
    let channel = endpoint.connect().await.map_err(|err| format!("{err:?}"))?;
    Ok(EsaServiceClient::new(channel))
}

/// Creates a session and probes it: Ok when the server answered both.
async fn round_trip(client: &mut EsaServiceClient<Channel>, id: &str) -> Result<(), tonic::Status> {
    client
        .create_session(pb::CreateSessionRequest {
            session_id: id.into(),
            config: Some(config(1)),
            progress: None,
        })
        .await?;
    let probe = client
        .probe(pb::ProbeRequest {
            session_id: id.into(),
            step: 0,
            action: vec![0.5],
            episode_start: true,
            ..Default::default()
        })
        .await?
        .into_inner();
    assert_eq!(probe.probe.len(), 1);
    Ok(())
}

/// Asserts that a client that should be refused gets nothing served: its connection fails,
/// or (TLS 1.3 reports a rejected client certificate after the client's side of the
/// handshake) its first call does.
async fn assert_refused(client: Result<EsaServiceClient<Channel>, String>, who: &str) {
    match client {
        Err(_) => {}
        Ok(mut client) => {
            let outcome = tokio::time::timeout(CONNECT * 2, round_trip(&mut client, who)).await;
            assert!(
                matches!(outcome, Ok(Err(_))),
                "{who} was served (or hung): {outcome:?}"
            );
        }
    }
}

#[tokio::test]
async fn a_tls_server_serves_clients_that_trust_its_ca_and_refuses_others() {
    let pki = Pki::new("esa test CA");
    let leaf = pki.leaf("esa-server");
    let server = start_with(EsaServer::builder().tls(TlsSettings::new(leaf.cert, leaf.key))).await;

    let mut trusting = tls_client(server.addr, &pki.ca_pem(), None)
        .await
        .expect("a client trusting the CA connects");
    round_trip(&mut trusting, "trusted").await.expect("served");

    assert_refused(plaintext_client(server.addr).await, "plaintext").await;
    let stranger_ca = Pki::new("another CA");
    assert_refused(
        tls_client(server.addr, &stranger_ca.ca_pem(), None).await,
        "wrong-ca",
    )
    .await;

    // Refused handshakes leave the server serving.
    round_trip(&mut trusting, "trusted-again")
        .await
        .expect("still served");
    server.stop().await;
}

#[tokio::test]
async fn with_a_client_ca_only_clients_with_its_certificates_are_served() {
    let server_pki = Pki::new("server CA");
    let client_pki = Pki::new("client CA");
    let leaf = server_pki.leaf("esa-server");
    let settings = TlsSettings::new(leaf.cert, leaf.key).client_ca(client_pki.ca_pem());
    assert!(settings.is_mutual());
    let server = start_with(EsaServer::builder().tls(settings)).await;
    let ca = server_pki.ca_pem();

    let trainer = client_pki.leaf("trainer");
    let mut owner = tls_client(server.addr, &ca, Some(&trainer))
        .await
        .expect("a client with a certificate from the client CA connects");
    round_trip(&mut owner, "mutual").await.expect("served");

    assert_refused(tls_client(server.addr, &ca, None).await, "no-cert").await;
    // Issued by the server's CA, which is not the one clients are checked against.
    let forged = server_pki.leaf("intruder");
    assert_refused(
        tls_client(server.addr, &ca, Some(&forged)).await,
        "other-ca-cert",
    )
    .await;
    assert_refused(plaintext_client(server.addr).await, "plaintext").await;

    round_trip(&mut owner, "mutual-again")
        .await
        .expect("still served");
    server.stop().await;
}

fn counter(server: &crate::common::TestServer, name: &str) -> u64 {
    let text = server.handler.render_metrics();
    text.lines()
        .find_map(|line| line.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in\n{text}"))
}

/// The connection limit tells busy from idle connections over TLS too, so a newcomer
/// cannot push out a connection whose StepStream is open.
#[tokio::test]
async fn over_tls_a_connection_with_a_call_in_flight_is_not_evicted() {
    let pki = Pki::new("esa test CA");
    let leaf = pki.leaf("esa-server");
    let builder = EsaServer::builder()
        .tls(TlsSettings::new(leaf.cert, leaf.key))
        .max_connections(1);
    let server = start_with(builder).await;
    let mut busy = tls_client(server.addr, &pki.ca_pem(), None)
        .await
        .expect("connects");
    let stream = Stream::open(&mut busy).await;
    assert_refused(
        tls_client(server.addr, &pki.ca_pem(), None).await,
        "newcomer",
    )
    .await;
    assert_eq!(counter(&server, "esa_connections_evicted_total"), 0);
    assert!(counter(&server, "esa_connections_refused_total") >= 1);
    drop(stream);
    server.stop().await;
}

/// Runs the executable with `args` until it exits (at most 30 s); returns its exit code and
/// stderr.
fn run_to_exit(args: &[&str]) -> (Option<i32>, String) {
    let mut child = Command::new(BIN)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start esa-server");
    let deadline = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("esa-server {args:?} did not exit");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .expect("piped stderr")
        .read_to_string(&mut stderr)
        .expect("read stderr");
    (status.code(), stderr)
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write test file");
    path.to_str().expect("utf-8 path").to_string()
}

#[test]
fn unusable_certificate_files_stop_the_server_with_a_clear_message() {
    let dir = tempfile::tempdir().expect("temp dir");
    let pki = Pki::new("esa test CA");
    let leaf = pki.leaf("esa-server");
    let other = pki.leaf("other");
    let cert = write(dir.path(), "cert.pem", &leaf.cert);
    let key = write(dir.path(), "key.pem", &leaf.key);
    let other_key = write(dir.path(), "other-key.pem", &other.key);
    let garbage = write(dir.path(), "garbage.pem", "not a certificate\n");
    let broken = write(
        dir.path(),
        "broken.pem",
        "-----BEGIN CERTIFICATE-----\nbm90IGEgY2VydGlmaWNhdGU=\n-----END CERTIFICATE-----\n",
    );
    let missing = dir.path().join("missing.pem");
    let missing = missing.to_str().expect("utf-8 path");

    let cases: [(&[&str], &[&str]); 7] = [
        (
            &["--tls-cert", missing, "--tls-key", &key],
            &["--tls-cert", missing],
        ),
        (
            &["--tls-cert", &cert, "--tls-key", missing],
            &["--tls-key", missing],
        ),
        (
            &["--tls-cert", &garbage, "--tls-key", &key],
            &["--tls-cert", "PEM"],
        ),
        (
            &["--tls-cert", &cert, "--tls-key", &cert],
            &["--tls-key", "PRIVATE KEY"],
        ),
        (
            &["--tls-cert", &broken, "--tls-key", &key],
            &["--tls-cert", "TLS"],
        ),
        // rustls checks that the key is the certificate's.
        (
            &["--tls-cert", &cert, "--tls-key", &other_key],
            &["--tls-key", "TLS"],
        ),
        (
            &[
                "--tls-cert",
                &cert,
                "--tls-key",
                &key,
                "--tls-client-ca",
                &garbage,
            ],
            &["--tls-client-ca", &garbage],
        ),
    ];
    for (flags, needles) in cases {
        let args = [&["--listen", "127.0.0.1:0"], flags].concat();
        let (code, stderr) = run_to_exit(&args);
        assert_eq!(code, Some(1), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
        for needle in needles {
            assert!(
                stderr.contains(needle),
                "{args:?}: no {needle:?} in {stderr}"
            );
        }
    }
}

#[tokio::test]
async fn the_executable_serves_tls_with_the_flags() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server_pki = Pki::new("server CA");
    let client_pki = Pki::new("client CA");
    let leaf = server_pki.leaf("esa-server");
    let cert = write(dir.path(), "cert.pem", &leaf.cert);
    let key = write(dir.path(), "key.pem", &leaf.key);
    let client_ca = write(dir.path(), "client-ca.pem", &client_pki.ca_pem());
    let (mut child, mut stdout) = launch(&[
        "--listen",
        "127.0.0.1:0",
        "--tls-cert",
        &cert,
        "--tls-key",
        &key,
        "--tls-client-ca",
        &client_ca,
    ]);
    let addr: SocketAddr = read_line_after(&mut stdout, "listening on ")
        .parse()
        .expect("a socket address");
    let trainer = client_pki.leaf("trainer");
    let mut client = tls_client(addr, &server_pki.ca_pem(), Some(&trainer))
        .await
        .expect("connects over mutual TLS");
    round_trip(&mut client, "cli").await.expect("served");
    assert_refused(plaintext_client(addr).await, "plaintext").await;
    assert_refused(
        tls_client(addr, &server_pki.ca_pem(), None).await,
        "no-cert",
    )
    .await;
    let _ = child.kill();
    let _ = child.wait();
}
