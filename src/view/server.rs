//! The HTTP side of the view: `tiny_http` on a loopback address, one thread per request, the
//! page and its colour maps from the binary, server-sent events for updates.
//!
//! Routes (every one needs `?token=…`; without it: 403):
//! - `/`: the page;
//! - `/events`: the event stream (`hello`, `scan`, `points`, `status`, `scans`, `figures`,
//!   `instrument`; see [`super::hub`]);
//! - `/api/state`: everything at once, as JSON;
//! - `/api/scan/N`: scan N of the list, read from its file (axes, the three channels, metadata);
//! - `/figure/N`: figure N of the list.

use super::hub::{Cursor, Hub};
use crate::plot::Colormap;
use serde_json::{json, Value};
use std::io::Write;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;

const PAGE: &str = include_str!("page.html");

/// Keep-alive comment interval on an idle event stream (a closed browser is noticed by the
/// next write).
const KEEPALIVE: Duration = Duration::from_secs(10);

/// The page with the colour maps filled in (the same ones `plot()` uses).
fn page() -> String {
    let table = |m: Colormap| {
        let v: Vec<[u8; 3]> = (0..256)
            .map(|i| {
                let (r, g, b) = m.rgb(i as f64 / 255.0);
                [r, g, b]
            })
            .collect();
        json!(v).to_string()
    };
    PAGE.replace("/*VIRIDIS*/[]", &table(Colormap::Sequential))
        .replace("/*RDBU*/[]", &table(Colormap::Diverging))
}

/// Resolve a host name for the view; only loopback addresses are allowed.
pub fn loopback(host: &str) -> Result<IpAddr, String> {
    let ip: IpAddr = match host {
        "localhost" => IpAddr::from([127, 0, 0, 1]),
        h => h.trim_matches(['[', ']']).parse().map_err(|_| {
            format!("view: host = {host:?} is not an IP address; the view serves 127.0.0.1, ::1 or localhost only")
        })?,
    };
    if !ip.is_loopback() {
        return Err(format!(
            "view: host = {host:?} is not a loopback address; the view serves this computer only \
             (127.0.0.1, ::1 or localhost): it shows the instrument to anyone who can reach it"
        ));
    }
    Ok(ip)
}

/// A running server.
pub struct Server {
    http: Arc<tiny_http::Server>,
    pub addr: SocketAddr,
    pub token: String,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Server {
    /// Serve `hub` on `host:port` (port 0: a free one).
    pub fn start(host: &str, port: u16, hub: Arc<Hub>) -> Result<Server, String> {
        let ip = loopback(host)?;
        let http = tiny_http::Server::http(SocketAddr::new(ip, port))
            .map_err(|e| format!("view: cannot listen on {ip}:{port}: {e}"))?;
        let addr = http
            .server_addr()
            .to_ip()
            .ok_or("view: the server has no IP address")?;
        let token = new_token();
        let http = Arc::new(http);
        let (h, t) = (http.clone(), token.clone());
        let thread = std::thread::Builder::new()
            .name("bfpscope-view".into())
            .spawn(move || {
                for req in h.incoming_requests() {
                    let (hub, t) = (hub.clone(), t.clone());
                    let _ = std::thread::Builder::new()
                        .name("bfpscope-view-req".into())
                        .spawn(move || handle(req, &hub, &t));
                }
            })
            .map_err(|e| format!("view: cannot start the server thread: {e}"))?;
        Ok(Server {
            http,
            addr,
            token,
            thread: Some(thread),
        })
    }

    /// The page's address with its token.
    pub fn url(&self) -> String {
        format!("http://{}/?token={}", self.addr, self.token)
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.http.unblock();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// 128 random bits as hex.
fn new_token() -> String {
    use rand::RngCore;
    let mut b = [0u8; 16];
    rand::rng().fill_bytes(&mut b);
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn query_param<'a>(query: &'a str, key: &str) -> Option<&'a str> {
    query
        .split('&')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| *k == key)
        .map(|(_, v)| v)
}

/// Constant-time comparison of the token (no early exit on the first differing byte).
fn token_ok(given: Option<&str>, token: &str) -> bool {
    let Some(g) = given else { return false };
    g.len() == token.len()
        && g.bytes()
            .zip(token.bytes())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
}

fn header(name: &str, value: &str) -> tiny_http::Header {
    tiny_http::Header::from_bytes(name.as_bytes(), value.as_bytes())
        .unwrap_or_else(|_| tiny_http::Header::from_bytes(&b"X-Bad"[..], &b"1"[..]).unwrap())
}

fn text(status: u16, body: &str) -> tiny_http::Response<std::io::Cursor<Vec<u8>>> {
    tiny_http::Response::from_string(body)
        .with_status_code(status)
        .with_header(header("Content-Type", "text/plain; charset=utf-8"))
}

fn json_response(v: &Value) -> tiny_http::Response<std::io::Cursor<Vec<u8>>> {
    tiny_http::Response::from_string(v.to_string())
        .with_header(header("Content-Type", "application/json"))
        .with_header(header("Cache-Control", "no-store"))
}

fn handle(req: tiny_http::Request, hub: &Hub, token: &str) {
    let url = req.url().to_string();
    let (path, query) = url.split_once('?').unwrap_or((url.as_str(), ""));
    let local = req.remote_addr().is_some_and(|a| a.ip().is_loopback());
    if !local || !token_ok(query_param(query, "token"), token) {
        let _ = req.respond(text(
            403,
            "403 Forbidden: bfpscope's view needs the address with its token, as printed by \
             `bfpscope repl --view` or view()\n",
        ));
        return;
    }
    if *req.method() != tiny_http::Method::Get {
        let _ = req.respond(text(405, "the view only reads: GET only\n"));
        return;
    }
    match path {
        "/" | "/index.html" => {
            let _ = req.respond(
                tiny_http::Response::from_string(page())
                    .with_header(header("Content-Type", "text/html; charset=utf-8"))
                    .with_header(header("Cache-Control", "no-store")),
            );
        }
        "/events" => events(req, hub),
        "/api/state" => {
            let _ = req.respond(json_response(&hub.snapshot()));
        }
        p if p.starts_with("/api/scan/") => {
            let n = p["/api/scan/".len()..].parse::<u64>().ok();
            let Some(file) = n.and_then(|n| hub.scan_path(n)) else {
                let _ = req.respond(text(404, "no such scan in the session list\n"));
                return;
            };
            match crate::data::npz::load_scan(&file) {
                Ok(scan) => {
                    let _ = req.respond(json_response(&scan_json(&scan)));
                }
                Err(e) => {
                    let _ = req.respond(text(500, &format!("{}: {e}\n", file.display())));
                }
            }
        }
        p if p.starts_with("/figure/") => {
            let n = p["/figure/".len()..].parse::<usize>().ok();
            let Some(file) = n.and_then(|n| hub.figure_path(n)) else {
                let _ = req.respond(text(404, "no such figure\n"));
                return;
            };
            let kind = if file.extension().is_some_and(|e| e == "svg") {
                "image/svg+xml"
            } else {
                "image/png"
            };
            match std::fs::read(&file) {
                Ok(bytes) => {
                    let _ = req.respond(
                        tiny_http::Response::from_data(bytes)
                            .with_header(header("Content-Type", kind))
                            .with_header(header("Cache-Control", "no-store")),
                    );
                }
                Err(e) => {
                    let _ = req.respond(text(404, &format!("{}: {e}\n", file.display())));
                }
            }
        }
        _ => {
            let _ = req.respond(text(404, "not found\n"));
        }
    }
}

/// A saved scan for the page: axes, the three channels row by row (null where not measured),
/// metadata.
fn scan_json(scan: &crate::data::Scan) -> Value {
    let ch = |im: &crate::data::Image| -> Vec<Option<f64>> {
        im.data
            .iter()
            .map(|v| v.is_finite().then_some(*v))
            .collect()
    };
    json!({
        "rows": scan.sx.data.nrows(),
        "cols": scan.sx.data.ncols(),
        "x": scan.sx.x,
        "y": scan.sx.y,
        "x_name": scan.sx.x_name,
        "y_name": scan.sx.y_name,
        "sx": ch(&scan.sx),
        "sy": ch(&scan.sy),
        "sz": ch(&scan.sz),
        "status": scan.status,
        "meta": scan.meta,
    })
}

/// The event stream of one browser tab: everything measured so far, then what follows.
fn events(req: tiny_http::Request, hub: &Hub) {
    let mut w = req.into_writer();
    let head = "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n\
                Connection: keep-alive\r\n\r\nretry: 1000\n\n";
    if w.write_all(head.as_bytes())
        .and_then(|_| w.flush())
        .is_err()
    {
        return;
    }
    let mut cur = Cursor::default();
    let mut buf = String::new();
    while hub.next_events(&mut cur, KEEPALIVE, &mut buf) {
        if buf.is_empty() {
            buf.push_str(": keep-alive\n\n");
        }
        if w.write_all(buf.as_bytes()).and_then(|_| w.flush()).is_err() {
            return; // the tab is gone
        }
        // batch the points of the next ~50 ms into one event
        std::thread::sleep(super::hub::SCAN_POLL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_loopback_hosts() {
        assert!(loopback("127.0.0.1").is_ok());
        assert!(loopback("localhost").is_ok());
        assert!(loopback("::1").is_ok());
        for host in ["0.0.0.0", "192.168.1.10"] {
            let e = loopback(host).unwrap_err();
            let said = format!("host = \"{host}\" is not a loopback address");
            assert!(e.contains(&said), "{e}");
        }
        assert!(loopback("example.org")
            .unwrap_err()
            .contains("not an IP address"));
    }

    #[test]
    fn token_comparison() {
        assert!(token_ok(Some("abc"), "abc"));
        assert!(!token_ok(Some("abd"), "abc"));
        assert!(!token_ok(Some("ab"), "abc"));
        assert!(!token_ok(None, "abc"));
        assert_eq!(query_param("a=1&token=xyz", "token"), Some("xyz"));
    }

    #[test]
    fn page_carries_both_colour_maps() {
        let p = page();
        assert!(!p.contains("/*VIRIDIS*/[]") && !p.contains("/*RDBU*/[]"));
        // viridis starts at matplotlib's #440154, RdBu (reversed) is white in the middle
        assert!(p.contains("[[68,1,84],"), "viridis table missing");
        assert!(p.contains("[5,48,97],"), "RdBu table missing");
    }
}
