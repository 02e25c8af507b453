//! Binding family `view`: the live view in the browser (`view()`), which `bfpscope repl --view`
//! starts too. The view only reads; see `src/view/`.

use super::ctx::Ctx;
use super::registry::{fail, Doc, Opt, Opts, RResult, Registrar, Spec};
use rhai::Map;
use std::sync::{Arc, Weak};
use std::time::Duration;

/// The options of this family's bindings, each key written once (`Opt`).
const HOST: Opt = Opt::new("host", "string", "");
const PORT: Opt = Opt::new("port", "int", "");

/// The address the view listens on unless `host` says otherwise.
const DEFAULT_HOST: &str = "127.0.0.1";

/// How often the instrument's state is refreshed while no scan runs.
const IDLE_REFRESH: Duration = Duration::from_secs(1);

/// Start the view on `host:port` (0: a free port) unless one runs; returns its address.
pub fn start_view(ctx: &Arc<Ctx>, host: &str, port: u16) -> Result<String, String> {
    // the rules hold also when a view already runs
    crate::view::server::loopback(host)?;
    if let Some(url) = ctx.view_url() {
        let running = ctx.view_port().unwrap_or(0);
        if port != 0 && port != running {
            return Err(format!(
                "view: port = {port}: the view already runs at {url} (one view per session)"
            ));
        }
        return Ok(url);
    }
    let view = crate::view::View::start(host, port, ctx.store.dir())?;
    let url = view.url();
    let hub = view.hub.clone();
    ctx.set_view(Some(view));
    if let Some(g) = ctx.instrument_glance() {
        hub.set_instrument(with_time(g));
    }
    spawn_refresher(Arc::downgrade(ctx));
    Ok(url)
}

fn with_time(mut v: serde_json::Value) -> serde_json::Value {
    v["updated"] = serde_json::json!(crate::data::clock::utc_now());
    v
}

/// While the workbench and its view live: every second without a scan, read the instrument's
/// position (only when nothing else holds the instrument) for the page.
fn spawn_refresher(ctx: Weak<Ctx>) {
    let _ = std::thread::Builder::new()
        .name("bfpscope-view-refresh".into())
        .spawn(move || loop {
            std::thread::sleep(IDLE_REFRESH);
            let Some(c) = ctx.upgrade() else { return };
            let Some(hub) = c.view_hub() else { return };
            if !hub.scanning() {
                if let Some(g) = c.instrument_glance() {
                    hub.set_instrument(with_time(g));
                }
            }
        });
}

pub fn register(r: &mut Registrar) {
    let d = Doc::func("view")
        .map(
            "options",
            "where to serve (all optional)",
            &[
                PORT.doc("optional: TCP port (default 0: a free one)"),
                HOST.doc(format!("optional: loopback address, {DEFAULT_HOST:?} (default), \"::1\" or \"localhost\"; any other is refused").as_str()),
            ],
        )
        .form("view() -> string")
        .returns("string", "the page's address, with its token")
        .summary("open the live view: a local web page that shows every scan while it runs, the session's scans, the figures and the instrument")
        .help(
            "Starts a small web server on this computer only (127.0.0.1) and prints its address; open it in a \
             browser beside the prompt. The page shows the scan in progress (Sx, Sy, Sz filling in point by point, \
             axes in µm, colour bar, the value and stage coordinates under the pointer, progress and ETA; line and \
             z scans as line plots), the list of this session's scans (click one to see it), each figure as it is \
             written, and the stage position and the last error. The address carries a random token: a request \
             without it is refused (403). The view only reads: motion goes through the prompt. Calling view() again \
             returns the same address. `bfpscope repl --view` starts it with the prompt.",
        )
        .example("view().starts_with(\"http://127.0.0.1:\")", "true")
        .example("view() == view()", "true")
        .example("view(#{host: \"0.0.0.0\"})", "error: view: host = \"0.0.0.0\" is not a loopback address")
        .example("view(#{port: 70000})", "error: view: port = 70000 is out of range")
        .example("view(); view(#{host: \"0.0.0.0\"})", "error: view: host = \"0.0.0.0\" is not a loopback address");
    let spec = d.spec();
    r.bind_ctx(d, |c| move |m: Map| view(&c, &spec, &m));
    let c = r.ctx();
    r.overload("view", move || open_view(&c, DEFAULT_HOST, 0));
}

/// `view(#{port, host})`: check the options, then [`open_view`].
fn view(ctx: &Arc<Ctx>, spec: &Spec, m: &Map) -> RResult<String> {
    let o = Opts::new(spec, m)?;
    let port = match o.int(PORT)? {
        Some(p) if !(0..=65535).contains(&p) => {
            return fail(format!(
                "view: port = {p} is out of range: 0 ≤ port ≤ 65535 (0: a free port)"
            ))
        }
        p => p.unwrap_or(0) as u16,
    };
    let host = o.string(HOST)?.unwrap_or_else(|| DEFAULT_HOST.into());
    open_view(ctx, &host, port)
}

/// `view()`: start the view (or find the running one) and print its address.
fn open_view(ctx: &Arc<Ctx>, host: &str, port: u16) -> RResult<String> {
    let url = start_view(ctx, host, port)?;
    ctx.print(&format!("live view: {url}"));
    Ok(url)
}
