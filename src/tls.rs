//! TLS for both listeners (rustls with the *ring* provider), from a PEM certificate chain
//! and private key (`--tls-cert`, `--tls-key`).
//!
//! Handshakes are done by [`crate::conn`], each in its connection's own task under
//! `--tls-handshake-timeout`, for both listeners.

use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context};
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::{self, ServerConfig};

/// The certificate chain and key, read and checked once at startup for both listeners.
#[derive(Clone)]
pub struct Tls {
    /// The rustls configuration of the HTTP listener (ALPN: h2, http/1.1).
    pub http: Arc<ServerConfig>,
    /// The gRPC listener's (ALPN: h2).
    pub grpc: Arc<ServerConfig>,
}

impl Tls {
    /// Both files or neither: one without the other is a configuration error. Reading
    /// fails, naming the file, when a file is unreadable, holds no PEM certificate or key,
    /// or when the key does not go with the certificate.
    pub fn load(cert: Option<&Path>, key: Option<&Path>) -> anyhow::Result<Option<Tls>> {
        let (cert, key) = match (cert, key) {
            (None, None) => return Ok(None),
            (Some(cert), Some(key)) => (cert, key),
            _ => bail!("--tls-cert and --tls-key go together: give both or neither"),
        };
        let cert_pem = std::fs::read(cert).with_context(|| format!("cannot read {}", cert.display()))?;
        let key_pem = std::fs::read(key).with_context(|| format!("cannot read {}", key.display()))?;
        let chain: Vec<CertificateDer<'static>> =
            CertificateDer::pem_slice_iter(&cert_pem)
                .collect::<Result<_, _>>()
                .with_context(|| format!("{}: not a PEM certificate chain", cert.display()))?;
        if chain.is_empty() {
            bail!("{}: no certificate found (expected PEM `BEGIN CERTIFICATE` blocks)", cert.display());
        }
        let private_key = PrivateKeyDer::from_pem_slice(&key_pem)
            .with_context(|| format!("{}: no PEM private key found (PKCS#8, PKCS#1 or SEC1)", key.display()))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut http = ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .context("TLS protocol versions")?
            .with_no_client_auth()
            .with_single_cert(chain, private_key)
            .with_context(|| format!("{} does not go with {}", key.display(), cert.display()))?;
        let mut grpc = http.clone();
        grpc.alpn_protocols = vec![b"h2".to_vec()];
        http.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
        Ok(Some(Tls { http: Arc::new(http), grpc: Arc::new(grpc) }))
    }
}
