//! The live view: a local web page beside the prompt that shows the scan in progress (Sx, Sy,
//! Sz filling in point by point), the session's scans, the figures as they are written and the
//! instrument's state.
//!
//! - [`hub`]: what the page shows, written by the scan engine (as its
//!   [`ScanObserver`](crate::acquire::ScanObserver)) and the bindings, read by the browsers.
//! - [`server`]: `tiny_http` on a loopback address with a random token; the page (one HTML file
//!   with its script and style, and the colour maps of `plot`) ships in the binary.
//!
//! The view only reads: every motion goes through the engine at the prompt. Why `tiny_http` and
//! server-sent events: docs/guide.md, "The live view".

pub mod hub;
pub mod server;

pub use hub::Hub;

use std::path::Path;
use std::sync::Arc;

/// A running view: its state and its server. Dropping it stops the server and every stream.
pub struct View {
    pub hub: Arc<Hub>,
    server: server::Server,
}

impl View {
    /// Serve on `host` (a loopback address) and `port` (0: a free one). The session's scans
    /// already in `session_dir` are listed.
    pub fn start(host: &str, port: u16, session_dir: &Path) -> Result<View, String> {
        let hub = Arc::new(Hub::new());
        list_session(&hub, session_dir);
        let server = server::Server::start(host, port, hub.clone())?;
        Ok(View { hub, server })
    }

    /// The page's address with its token (`http://127.0.0.1:PORT/?token=…`).
    pub fn url(&self) -> String {
        self.server.url()
    }

    /// The address served.
    pub fn addr(&self) -> std::net::SocketAddr {
        self.server.addr
    }
}

impl Drop for View {
    fn drop(&mut self) {
        self.hub.close();
    }
}

/// Add the numbered scans already in the session folder to the list (unreadable files are
/// skipped: the list shows what can be opened).
fn list_session(hub: &Hub, dir: &Path) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    let mut files: Vec<(u64, std::path::PathBuf)> = rd
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            crate::data::session::scan_number(&e.file_name().to_string_lossy())
                .map(|n| (n, e.path()))
        })
        .collect();
    files.sort();
    for (_, p) in files {
        if let Ok(scan) = crate::data::npz::load_scan(&p) {
            hub.add_saved_scan(&p, &scan);
        }
    }
}
