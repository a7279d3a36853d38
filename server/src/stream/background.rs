//! A server on a thread of its own (its own tokio runtime), stopped when dropped: for programs and
//! tests that embed one beside other work.

use super::{serve_on, ServeConfig, ServeError, Shared};
use std::path::Path;
use std::time::Duration;

/// A store served on a background thread until dropped (its runtime ends, and every connection
/// with it).
pub struct BackgroundServer {
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    url: String,
}

impl BackgroundServer {
    /// Serves `store` on `addr` (`127.0.0.1:0`: any free port) with `config`; returns once it
    /// listens.
    pub fn start(store: &Path, addr: &str, config: ServeConfig) -> Result<Self, ServeError> {
        let shared = Shared::open(store, config)?;
        let bind = addr.to_string();
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = match tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
            {
                Ok(rt) => rt,
                Err(e) => {
                    let _ = addr_tx.send(Err(e));
                    return;
                }
            };
            rt.block_on(async move {
                let listener = match tokio::net::TcpListener::bind(&bind).await {
                    Ok(l) => l,
                    Err(e) => {
                        let _ = addr_tx.send(Err(e));
                        return;
                    }
                };
                let _ = addr_tx.send(listener.local_addr());
                tokio::select! {
                    r = serve_on(listener, shared) => {
                        if let Err(e) = r {
                            tracing::error!("the background server stopped: {e}");
                        }
                    }
                    _ = stop_rx => {}
                }
            });
        });
        let bound = addr_rx
            .recv_timeout(Duration::from_secs(20))
            .map_err(|_| ServeError::Io(std::io::Error::other("the server thread did not start")))?
            .map_err(|source| ServeError::Bind {
                addr: addr.to_string(),
                source,
            })?;
        Ok(BackgroundServer {
            stop: Some(stop_tx),
            thread: Some(thread),
            url: format!("http://{bound}"),
        })
    }

    /// `http://host:port` of the listening socket.
    pub fn url(&self) -> &str {
        &self.url
    }
}

impl Drop for BackgroundServer {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
