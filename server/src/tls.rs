//! TLS on the gRPC listener: the server's certificate and key, and, for
//! mutual TLS, the CA that client certificates must chain to.
//!
//! Files are read and checked when the settings are made, so a missing,
//! unreadable or malformed file stops the server before it announces
//! `listening on`, with a message naming the flag and the file.

use std::path::Path;
use std::time::Duration;

use tonic::transport::{Certificate, Identity, ServerTlsConfig};

use crate::error::{io_context, StartError};

/// PEM material for TLS on the gRPC listener.
#[derive(Clone)]
pub struct TlsSettings {
    cert_pem: Vec<u8>,
    key_pem: Vec<u8>,
    client_ca_pem: Option<Vec<u8>>,
}

/// The key stays out of logs and debug output.
impl std::fmt::Debug for TlsSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TlsSettings")
            .field("mutual", &self.client_ca_pem.is_some())
            .finish_non_exhaustive()
    }
}

impl TlsSettings {
    /// TLS with this PEM certificate chain (server certificate first) and its PEM private key
    /// (PKCS#8, SEC1 or PKCS#1).
    pub fn new(cert_pem: impl Into<Vec<u8>>, key_pem: impl Into<Vec<u8>>) -> Self {
        Self {
            cert_pem: cert_pem.into(),
            key_pem: key_pem.into(),
            client_ca_pem: None,
        }
    }

    /// Requires every client to present a certificate issued by one of these PEM CA
    /// certificates (mutual TLS); a client without one fails the handshake.
    pub fn client_ca(mut self, ca_pem: impl Into<Vec<u8>>) -> Self {
        self.client_ca_pem = Some(ca_pem.into());
        self
    }

    /// Whether clients must present a certificate.
    pub fn is_mutual(&self) -> bool {
        self.client_ca_pem.is_some()
    }

    /// Reads the files behind `--tls-cert`, `--tls-key` and `--tls-client-ca`, and checks that
    /// they make a usable server configuration.
    pub fn from_files(
        cert: &Path,
        key: &Path,
        client_ca: Option<&Path>,
    ) -> Result<Self, StartError> {
        let cert_pem = read_pem(cert, "--tls-cert", "CERTIFICATE")?;
        let key_pem = read_pem(key, "--tls-key", "PRIVATE KEY")?;
        warn_if_shared(key);
        let mut settings = Self::new(cert_pem, key_pem);
        if let Some(ca) = client_ca {
            settings = settings.client_ca(read_pem(ca, "--tls-client-ca", "CERTIFICATE")?);
        }
        settings.check().map_err(|err| {
            let ca = client_ca
                .map(|ca| format!(", --tls-client-ca {}", ca.display()))
                .unwrap_or_default();
            StartError::Config(format!(
                "--tls-cert {}, --tls-key {}{ca}: {err}",
                cert.display(),
                key.display()
            ))
        })?;
        Ok(settings)
    }

    /// Builds the rustls configuration once, so that a certificate that does not match its key
    /// (or a CA file rustls cannot use) is an error now rather than at the first connection.
    pub fn check(&self) -> Result<(), StartError> {
        tonic::transport::Server::builder()
            .tls_config(self.server_config(Duration::from_secs(10)))
            .map(|_| ())
            .map_err(|err| StartError::Config(format!("unusable TLS settings: {}", chain(&err))))
    }

    /// tonic's configuration; `handshake_timeout` bounds each TLS handshake.
    pub(crate) fn server_config(&self, handshake_timeout: Duration) -> ServerTlsConfig {
        let config = ServerTlsConfig::new()
            .identity(Identity::from_pem(&self.cert_pem, &self.key_pem))
            .timeout(handshake_timeout);
        match &self.client_ca_pem {
            Some(ca) => config.client_ca_root(Certificate::from_pem(ca)),
            None => config,
        }
    }
}

/// The file's content if it holds a PEM block whose label ends with `label`.
fn read_pem(path: &Path, flag: &str, label: &str) -> Result<Vec<u8>, StartError> {
    let pem = std::fs::read(path)
        .map_err(|err| io_context(err, format!("{flag}: cannot read {}", path.display())))?;
    let text = String::from_utf8_lossy(&pem);
    let has_block = text.match_indices("-----BEGIN ").any(|(at, _)| {
        text[at..]
            .lines()
            .next()
            .is_some_and(|l| l.ends_with(&format!("{label}-----")))
    });
    if !has_block {
        return Err(StartError::Config(format!(
            "{flag}: expected a PEM file with a `-----BEGIN ...{label}-----` block in {}",
            path.display()
        )));
    }
    Ok(pem)
}

fn warn_if_shared(key: &Path) {
    use std::os::unix::fs::PermissionsExt as _;
    if let Ok(meta) = std::fs::metadata(key) {
        if meta.permissions().mode() & 0o077 != 0 {
            tracing::warn!(
                path = %key.display(),
                "the TLS key file is readable by other users; chmod 600 it"
            );
        }
    }
}

/// An error and its sources, `outer: inner: ...` (tonic's own message is only "transport error").
fn chain(err: &dyn std::error::Error) -> String {
    let mut text = err.to_string();
    let mut source = err.source();
    while let Some(inner) = source {
        text.push_str(": ");
        text.push_str(&inner.to_string());
        source = inner.source();
    }
    text
}
