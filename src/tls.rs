//! TLS for both listeners (rustls with the *ring* provider), from a PEM certificate chain
//! and private key (`--tls-cert`, `--tls-key`).
//!
//! gRPC uses tonic's own rustls acceptor. HTTP uses [`TlsListener`]: a TCP accept loop
//! that runs each handshake in its own task (bounded in number and time, so a client that
//! never finishes its handshake holds up no one) and hands finished connections to axum.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::{self, ServerConfig};
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;

/// A handshake not finished by then is dropped.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Handshakes in progress at once; further connections wait in the kernel's backlog.
const MAX_HANDSHAKES: usize = 256;

/// The certificate chain and key, read and checked once at startup for both listeners.
#[derive(Clone)]
pub struct Tls {
    /// The PEM texts, for tonic's `Identity` (gRPC).
    pub cert_pem: Vec<u8>,
    pub key_pem: Vec<u8>,
    /// The rustls configuration of the HTTP listener (ALPN: h2, http/1.1).
    pub http: Arc<ServerConfig>,
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
        http.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
        Ok(Some(Tls { cert_pem, key_pem, http: Arc::new(http) }))
    }
}

/// A TCP listener whose connections come out TLS-terminated (see the module docs).
pub struct TlsListener {
    ready: mpsc::Receiver<(TlsStream<TcpStream>, SocketAddr)>,
    local: SocketAddr,
    accept_loop: tokio::task::JoinHandle<()>,
}

impl TlsListener {
    pub fn new(tcp: TcpListener, config: Arc<ServerConfig>) -> std::io::Result<TlsListener> {
        let local = tcp.local_addr()?;
        let acceptor = TlsAcceptor::from(config);
        let (tx, ready) = mpsc::channel(64);
        let permits = Arc::new(Semaphore::new(MAX_HANDSHAKES));
        let accept_loop = tokio::spawn(async move {
            loop {
                let Ok(permit) = permits.clone().acquire_owned().await else { return };
                let (stream, peer) = match tcp.accept().await {
                    Ok(c) => c,
                    Err(e) => {
                        // Out of file descriptors and the like: wait instead of spinning.
                        tracing::warn!(error = %e, "cannot accept a connection");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let (acceptor, tx) = (acceptor.clone(), tx.clone());
                tokio::spawn(async move {
                    let _permit = permit;
                    match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await {
                        Ok(Ok(tls)) => {
                            let _ = tx.send((tls, peer)).await;
                        }
                        Ok(Err(e)) => tracing::debug!(%peer, error = %e, "TLS handshake failed"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                });
            }
        });
        Ok(TlsListener { ready, local, accept_loop })
    }
}

impl Drop for TlsListener {
    fn drop(&mut self) {
        self.accept_loop.abort();
    }
}

impl axum::serve::Listener for TlsListener {
    type Io = TlsStream<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.ready.recv().await {
            Some(connection) => connection,
            // The accept loop ended (it only does when dropped): no more connections.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<SocketAddr> {
        Ok(self.local)
    }
}
