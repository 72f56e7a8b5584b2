//! Token and (mutual) TLS against a spawned esa-server.

#[allow(dead_code)]
#[path = "../examples/control_loop.rs"]
mod example;

use std::time::Duration;

use esa_client::{Client, Kind, Options, Tls};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose, IsCa,
    KeyPair, KeyUsagePurpose,
};

/// A CA and one certificate for `localhost` (server and client alike): (ca, cert, key) PEMs.
fn pki() -> (String, String, String) {
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    params
        .distinguished_name
        .push(DnType::CommonName, "esa test CA");
    let ca = CertifiedIssuer::self_signed(params, KeyPair::generate().unwrap()).unwrap();
    let mut params = CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()]).unwrap();
    params.distinguished_name.push(DnType::CommonName, "esa");
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    params.use_authority_key_identifier_extension = true;
    let key = KeyPair::generate().unwrap();
    let cert = params.signed_by(&key, &ca).unwrap();
    (ca.pem(), cert.pem(), key.serialize_pem())
}

#[tokio::test]
async fn mutual_tls_and_a_token() {
    if example::server_binary().is_none() {
        eprintln!("skipped: no esa-server (set ESA_SERVER_BIN or build target/release)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = pki();
    let path = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_string()
    };
    let (ca_file, cert_file, key_file) = (
        path("ca.pem", &ca),
        path("cert.pem", &cert),
        path("key.pem", &key),
    );
    let token_file = path("token", "s3cret\n");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o600)).unwrap();
    }
    let server = example::Server::spawn_with(&[
        "--tls-cert",
        &cert_file,
        "--tls-key",
        &key_file,
        "--tls-client-ca",
        &ca_file,
        "--auth-token-file",
        &token_file,
    ])
    .unwrap();
    let tls = Tls::default().ca_pem(ca.clone()).domain("localhost");
    let options = Options::default().timeout(Duration::from_secs(5));

    // TLS and the client's certificate, no token: the server answers, and refuses.
    let mutual = tls.clone().identity(cert.clone(), key.clone());
    let client = Client::connect(&server.address, options.clone().tls(mutual.clone()))
        .await
        .unwrap();
    let err = client.end_episode("x").await.unwrap_err();
    assert_eq!(err.kind(), Kind::Unauthenticated, "{err}");

    // With the token: served (NOT_FOUND is the server's answer about the session).
    let client = Client::connect(&server.address, options.clone().tls(mutual).token("s3cret"))
        .await
        .unwrap();
    let err = client.end_episode("x").await.unwrap_err();
    assert_eq!(err.kind(), Kind::SessionNotFound, "{err}");
    let err = example::run(&server.address, 1).await.unwrap_err(); // plaintext to a TLS port
    assert_eq!(err.kind(), Kind::ServerUnavailable, "{err}");

    // Without a client certificate the mutual-TLS handshake fails: unavailable.
    let refused = match Client::connect(&server.address, options.tls(tls).token("s3cret")).await {
        Err(err) => err,
        Ok(client) => client.end_episode("x").await.unwrap_err(),
    };
    assert_eq!(refused.kind(), Kind::ServerUnavailable, "{refused}");
}
