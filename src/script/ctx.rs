//! The state every binding shares: settings (data folder, soft limits, sandbox), the connected
//! instrument, the abort flag, the optics and scene (for metadata), the script being run.

use super::doc::{fail, Doc, RResult};
use crate::acquire::{SessionStore, SoftLimits};
use crate::instrument::mock::MockHandle;
use crate::instrument::sim::{Renderer, Scene, SimConfig, SimCore};
use crate::instrument::Instrument;
use crate::optics::{OpticsError, ValidOptics};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};

/// Where text goes (stdout/stderr in the binary, a buffer in tests).
pub type Printer = Arc<dyn Fn(&str) + Send + Sync>;

/// Rhai sandbox limits (config `[sandbox]`, parsed by `config/`).
pub use crate::config::Sandbox;

/// How a workbench is set up (from the CLI and the config).
#[derive(Clone)]
pub struct Settings {
    /// Session folder for autosaved scans.
    pub data_dir: PathBuf,
    pub limits: SoftLimits,
    pub sandbox: Sandbox,
    /// Show progress bars (stderr is a terminal).
    pub progress: bool,
    /// `print` output and results.
    pub print: Printer,
    /// Operator messages: ETA, warnings (stderr).
    pub log: Printer,
    /// Set by Ctrl-C.
    pub abort: Arc<AtomicBool>,
    /// The config file, parsed once at start-up (`config::Config`), if any.
    pub config: Option<crate::config::Config>,
    pub config_path: Option<PathBuf>,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            data_dir: PathBuf::from("bfpscope_data"),
            limits: SoftLimits::default(),
            sandbox: Sandbox::default(),
            progress: false,
            print: Arc::new(out_line),
            log: Arc::new(err_line),
            abort: Arc::new(AtomicBool::new(false)),
            config: None,
            config_path: None,
        }
    }
}

impl Settings {
    /// Settings that capture `print` and log output into one shared string (tests).
    pub fn captured(data_dir: impl Into<PathBuf>) -> (Settings, Arc<Mutex<String>>) {
        let buf = Arc::new(Mutex::new(String::new()));
        let (b1, b2) = (buf.clone(), buf.clone());
        let s = Settings {
            data_dir: data_dir.into(),
            print: Arc::new(move |s| {
                let mut b = b1.lock().unwrap_or_else(|e| e.into_inner());
                b.push_str(s);
                b.push('\n');
            }),
            log: Arc::new(move |s| {
                let mut b = b2.lock().unwrap_or_else(|e| e.into_inner());
                b.push_str(s);
                b.push('\n');
            }),
            ..Settings::default()
        };
        (s, buf)
    }

    /// Apply the parsed config (validated by `config/`, its one owner): `[safety]` (soft
    /// limits, step and speed limits), `[sandbox]`, `[session] data_dir`; `[optics]` is read
    /// by [`Ctx::new`].
    pub fn apply_config(
        &mut self,
        config: crate::config::Config,
        path: Option<PathBuf>,
    ) -> Result<(), String> {
        self.limits = config.soft_limits();
        self.sandbox = config.sandbox;
        if let Some(d) = &config.session.data_dir {
            self.data_dir = PathBuf::from(d);
        }
        self.config = Some(config);
        self.config_path = path;
        Ok(())
    }
}

/// A line to stdout; a closed pipe (`bfpscope eval 'help()' | head`) is not an error.
pub fn out_line(s: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stdout().lock(), "{s}");
}

/// A line to stderr, ignoring a closed pipe.
pub fn err_line(s: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{s}");
}

/// The script (or REPL) whose actions are being recorded.
#[derive(Debug, Clone, Default)]
pub struct ScriptInfo {
    pub path: Option<PathBuf>,
    pub sha256: Option<String>,
    /// For the REPL: the line being run.
    pub line: Option<String>,
}

/// What comes with a connected instrument besides the `Instrument` itself.
#[derive(Default)]
pub struct Attached {
    /// The mock's command log (mock backend).
    pub mock: Option<MockHandle>,
    /// The simulator's core (sim backend): `simulate(scene)` re-scenes it.
    pub sim: Option<SimCore>,
    /// The renderer an emulated instrument images (its optics and scene).
    pub renderer: Option<Arc<Renderer>>,
    /// Whatever must live exactly as long as the connection (the in-process emulators of the
    /// `emulated` backend); dropped after the instrument on disconnect.
    pub keepalive: Option<Box<dyn std::any::Any + Send>>,
}

/// Shared state of one workbench.
pub struct Ctx {
    pub settings: Settings,
    instrument: Mutex<Option<Instrument>>,
    /// Backend name of the connected instrument (`mock`, `sim`, `hardware`, `emulated`).
    backend: Mutex<Option<String>>,
    pub(crate) mock: Mutex<Option<MockHandle>>,
    sim: Mutex<Option<SimCore>>,
    renderer: Mutex<Option<Arc<Renderer>>>,
    keepalive: Mutex<Option<Box<dyn std::any::Any + Send>>>,
    pub store: SessionStore,
    pub(crate) script: Mutex<ScriptInfo>,
    /// Optics of the set-up, validated, their beam resolved: the one copy, changed only by
    /// [`Ctx::set_optics`] (which rebuilds the simulator's renderer from them). The scene has
    /// no copy here: it is the one the connected simulator images ([`Ctx::scene`]).
    optics: Mutex<ValidOptics>,
    /// Protocols running (innermost last): #{name, args}, set by protocol_begin/protocol_end.
    pub protocols: Mutex<Vec<Value>>,
    /// The trace being recorded by `trace_start()` (golden traces of protocol runs).
    pub trace: Mutex<Option<crate::instrument::trace::Trace>>,
    /// Answers queued by `answer([...])` for `ask` (scripted tests of operator prompts).
    pub answers: Mutex<std::collections::VecDeque<String>>,
    /// Notes from `note("…")`, recorded in the metadata of every later scan (`notes`).
    pub notes: Mutex<Vec<String>>,
    pub(crate) docs: OnceLock<Arc<Vec<Doc>>>,
    git: OnceLock<Option<String>>,
    /// The live view, once `view()` or `repl --view` started it.
    view: Mutex<Option<crate::view::View>>,
    /// The partial scan of the last scan that did not complete (Ctrl-C, a device fault), for
    /// the prompt to bind to the variable being assigned (or `_`).
    partial: Mutex<Option<super::values::ScanRef>>,
    /// What a Ctrl-C during a scan asks (the prompt on a terminal sets it): `true` resumes.
    /// Unset, Ctrl-C aborts the scan.
    pause_question: Mutex<Option<PauseQuestion>>,
    /// Shows long text a screen at a time (the prompt on a terminal sets it); unset, `page`
    /// prints.
    pager: Mutex<Option<Pager>>,
    /// Everything printed (results aside) while the prompt records an entry for the session
    /// log: `print`, operator messages (ETA, saved paths, warnings), pages of help.
    transcript: Mutex<Option<String>>,
}

/// Shows a long text a page at a time (see [`Ctx::page`]).
pub type Pager = Arc<dyn Fn(&str) + Send + Sync>;

pub use crate::acquire::Paused;

/// The question a paused scan asks the operator (see [`crate::acquire::ScanEnv::pause`]).
pub type PauseQuestion = Arc<dyn Fn(&crate::acquire::Paused) -> bool + Send + Sync>;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Ctx {
    /// The session's optics (`set_optics`), recovering from a poisoned lock.
    pub fn optics(&self) -> ValidOptics {
        lock(&self.optics).clone()
    }

    /// Make `new` the session's optics. A connected simulator renders its scene in them from
    /// now on (its renderer is rebuilt first: on an error nothing changes). The emulated
    /// instrument keeps the optics it was connected with (its emulators render them), so it
    /// refuses new ones.
    pub fn set_optics(&self, new: ValidOptics) -> Result<(), OpticsError> {
        let mut optics = lock(&self.optics);
        if lock(&self.renderer).is_some() {
            return Err(OpticsError::Invalid(
                "the emulated instrument renders the optics it was connected with: connect(#{backend: \"sim\"}) or connect(#{backend: \"mock\"}), set_optics, then connect(#{backend: \"emulated\"}) again".into(),
            ));
        }
        if let Some(core) = self.sim_core() {
            core.set_scene(&new, &core.renderer().scene)?;
        }
        *optics = new;
        Ok(())
    }

    /// Put `scene` under the simulator in the session's optics: the connected simulator is
    /// re-scened (position and clock kept), or else a new simulated instrument imaging it is
    /// connected. The optics are held while the renderer is built, so a `set_optics` cannot
    /// come between.
    pub fn simulate_scene(&self, scene: &Scene) -> Result<SimCore, OpticsError> {
        let optics = lock(&self.optics);
        if let Some(core) = self.sim_core() {
            core.set_scene(&optics, scene)?;
            return Ok(core);
        }
        let core = SimCore::new(&*optics, scene, SimConfig::default())?;
        self.attach_sim(core.clone(), 0.01);
        Ok(core)
    }

    /// The scene the connected instrument images: the simulator's, or the emulated
    /// instrument's; `None` for the mock and for hardware.
    pub fn scene(&self) -> Option<Scene> {
        if let Some(core) = self.sim_core() {
            return Some(core.renderer().scene.clone());
        }
        lock(&self.renderer).as_ref().map(|r| r.scene.clone())
    }

    pub fn new(settings: Settings) -> Ctx {
        // `[optics]` of the config (validated when the file was read)
        let optics = settings
            .config
            .as_ref()
            .and_then(|c| c.optics.resolve().ok())
            .unwrap_or_default();
        Ctx {
            store: SessionStore::new(settings.data_dir.clone()),
            settings,
            instrument: Mutex::new(None),
            backend: Mutex::new(None),
            mock: Mutex::new(None),
            sim: Mutex::new(None),
            renderer: Mutex::new(None),
            keepalive: Mutex::new(None),
            script: Mutex::new(ScriptInfo::default()),
            optics: Mutex::new(optics),
            answers: Mutex::new(Default::default()),
            notes: Mutex::new(vec![]),
            trace: Mutex::new(None),
            protocols: Mutex::new(vec![]),
            docs: OnceLock::new(),
            git: OnceLock::new(),
            view: Mutex::new(None),
            partial: Mutex::new(None),
            pause_question: Mutex::new(None),
            pager: Mutex::new(None),
            transcript: Mutex::new(None),
        }
    }

    /// Start recording everything printed (for the session log); a recording running is
    /// replaced.
    pub fn start_transcript(&self) {
        *lock(&self.transcript) = Some(String::new());
    }

    /// Stop recording and return what was printed since [`Ctx::start_transcript`].
    pub fn take_transcript(&self) -> String {
        lock(&self.transcript).take().unwrap_or_default()
    }

    fn record(&self, s: &str) {
        if let Some(t) = lock(&self.transcript).as_mut() {
            t.push_str(s);
            if !s.ends_with('\n') {
                t.push('\n');
            }
        }
    }

    /// Long text (`help()`) goes through `p` from now on; `None`: printed whole.
    pub fn set_pager(&self, p: Option<Pager>) {
        *lock(&self.pager) = p;
    }

    /// Print long text a page at a time when the prompt set a pager (a terminal), else whole.
    pub fn page(&self, text: &str) {
        let pager = lock(&self.pager).clone();
        match pager {
            Some(p) => {
                self.record(text);
                p(text)
            }
            None => self.print(text),
        }
    }

    /// Ctrl-C during a scan pauses it and asks `q` (resume or abort); `None`: Ctrl-C aborts.
    pub fn set_pause_question(&self, q: Option<PauseQuestion>) {
        *lock(&self.pause_question) = q;
    }

    /// The pause question, if the prompt set one.
    pub fn pause_question(&self) -> Option<PauseQuestion> {
        lock(&self.pause_question).clone()
    }

    /// Keep the partial scan of a scan that ended early.
    pub fn set_partial(&self, scan: Option<super::values::ScanRef>) {
        *lock(&self.partial) = scan;
    }

    /// Take the partial scan kept by the last scan that ended early, if any.
    pub fn take_partial(&self) -> Option<super::values::ScanRef> {
        lock(&self.partial).take()
    }

    /// The running view's state (None when no view was started).
    pub fn view_hub(&self) -> Option<Arc<crate::view::Hub>> {
        lock(&self.view).as_ref().map(|v| v.hub.clone())
    }

    /// The running view's port, if any.
    pub fn view_port(&self) -> Option<u16> {
        lock(&self.view).as_ref().map(|v| v.addr().port())
    }

    /// The running view's address, if any.
    pub fn view_url(&self) -> Option<String> {
        lock(&self.view).as_ref().map(|v| v.url())
    }

    /// Keep `view` as this workbench's view (replacing and stopping an earlier one).
    pub fn set_view(&self, view: Option<crate::view::View>) {
        let old = std::mem::replace(&mut *lock(&self.view), view);
        drop(old);
    }

    /// What the view shows of the instrument, read only when nothing else is using it (a
    /// binding or a scan holds the instrument: `None`, try later). Reads the stage position.
    pub fn instrument_glance(&self) -> Option<Value> {
        let mut g = self.instrument.try_lock().ok()?;
        let backend = self.backend.try_lock().ok()?.clone();
        Some(match g.as_mut() {
            Some(inst) => {
                let (pos, err) = match inst.stage.position() {
                    Ok(p) => (json!(p), Value::Null),
                    Err(e) => (Value::Null, json!(e.to_string())),
                };
                json!({
                    "connected": true,
                    "backend": backend,
                    "stage": inst.stage.name(),
                    "qpd": inst.qpd.name(),
                    "position_um": pos,
                    "position_error": err,
                })
            }
            None => json!({ "connected": false, "backend": null, "position_um": null }),
        })
    }

    /// A figure was written: the view shows it.
    pub fn view_figure(&self, path: &std::path::Path) {
        if let Some(h) = self.view_hub() {
            h.add_figure(path);
        }
    }

    /// The operator saw this error: the view shows it as the last one.
    pub fn view_error(&self, message: &str) {
        if let Some(h) = self.view_hub() {
            h.set_error(message);
        }
    }

    /// Every binding declaration (available once the engine is built).
    pub fn docs(&self) -> Arc<Vec<Doc>> {
        self.docs.get().cloned().unwrap_or_default()
    }

    pub fn print(&self, s: &str) {
        self.record(s);
        (self.settings.print)(s)
    }
    pub fn log(&self, s: &str) {
        self.record(s);
        (self.settings.log)(s)
    }

    /// Say every warning of an answer of `who` to the operator (stderr and the session log):
    /// `who: warning: …`, one line each.
    pub fn warn_all(&self, who: &str, warnings: &[String]) {
        for w in warnings {
            self.log(&format!("{who}: warning: {w}"));
        }
    }

    /// Install an instrument (replacing the previous one). The backend name is `mock` with a
    /// mock handle, else the description's `backend` (`sim`, …), else `hardware`.
    pub fn connect(&self, inst: Instrument, mock: Option<MockHandle>) {
        let backend = if mock.is_some() {
            "mock".to_string()
        } else {
            inst.description["backend"]
                .as_str()
                .unwrap_or(crate::instrument::family::HARDWARE)
                .to_string()
        };
        self.attach(
            &backend,
            inst,
            Attached {
                mock,
                ..Attached::default()
            },
        );
    }

    /// Install an instrument under a backend name with what comes with it, replacing (and
    /// closing) the previous one.
    pub fn attach(&self, backend: &str, inst: Instrument, extra: Attached) {
        let _ = self.disconnect();
        *lock(&self.instrument) = Some(inst);
        *lock(&self.backend) = Some(backend.to_string());
        *lock(&self.mock) = extra.mock;
        *lock(&self.sim) = extra.sim;
        *lock(&self.renderer) = extra.renderer;
        *lock(&self.keepalive) = extra.keepalive;
    }

    /// Install the simulated instrument over `core`.
    pub fn attach_sim(&self, core: SimCore, settle_s: f64) {
        let inst = core.instrument(settle_s);
        self.attach(
            "sim",
            inst,
            Attached {
                sim: Some(core),
                ..Attached::default()
            },
        );
    }

    /// Drop the connected instrument (closing its ports), then what came with it (emulators
    /// stop). Returns the backend name of what was connected.
    pub fn disconnect(&self) -> Option<String> {
        let old = lock(&self.instrument).take();
        drop(old);
        *lock(&self.mock) = None;
        *lock(&self.sim) = None;
        *lock(&self.renderer) = None;
        let keep = lock(&self.keepalive).take();
        drop(keep);
        lock(&self.backend).take()
    }

    pub fn is_connected(&self) -> bool {
        lock(&self.instrument).is_some()
    }
    /// Backend name of the connected instrument (`mock`, `sim`, `hardware`, `emulated`).
    pub fn backend(&self) -> Option<String> {
        lock(&self.backend).clone()
    }
    /// The simulator's core when the simulated instrument is what is connected.
    pub fn sim_core(&self) -> Option<SimCore> {
        lock(&self.sim).clone()
    }
    /// The mock's handle when the mock instrument is connected.
    pub fn mock(&self) -> Option<MockHandle> {
        lock(&self.mock).clone()
    }

    /// Run `f` with the instrument; `who` names the binding in the error when none is connected.
    /// Wrap the connected instrument so every move and read is recorded (with the clock's time)
    /// into a fresh trace; a trace already running is replaced.
    pub fn trace_start(&self) -> RResult<()> {
        let mut g = lock(&self.instrument);
        let Some(inst) = g.take() else {
            return fail("trace_start: no instrument connected");
        };
        let (inst, trace) = inst.traced();
        *g = Some(inst);
        *lock(&self.trace) = Some(trace);
        Ok(())
    }

    /// Record a protocol's decision in the running trace (no-op when not tracing).
    pub fn trace_note(&self, what: &str) {
        if let Some(t) = lock(&self.trace).as_ref() {
            t.note(what);
        }
    }

    /// The running trace's text (None when not tracing).
    pub fn trace_text(&self) -> Option<String> {
        lock(&self.trace).as_ref().map(|t| t.text())
    }

    pub fn with_instrument<T>(
        &self,
        who: &str,
        f: impl FnOnce(&mut Instrument) -> RResult<T>,
    ) -> RResult<T> {
        let mut g = lock(&self.instrument);
        match g.as_mut() {
            Some(inst) => f(inst),
            None => fail(format!(
                "{who}: no instrument connected; connect one with connect() (what the config names), \
                 connect(#{{backend: \"sim\"}}) or connect(#{{backend: \"mock\"}})"
            )),
        }
    }

    pub fn set_script(&self, info: ScriptInfo) {
        *lock(&self.script) = info;
    }
    pub fn script(&self) -> ScriptInfo {
        lock(&self.script).clone()
    }

    /// Git revision of the working directory (`git rev-parse`), once per workbench.
    pub fn git_revision(&self) -> Option<String> {
        self.git
            .get_or_init(|| {
                let dir = self
                    .script()
                    .path
                    .and_then(|p| p.parent().map(|d| d.to_path_buf()))
                    .filter(|d| !d.as_os_str().is_empty())
                    .unwrap_or_else(|| PathBuf::from("."));
                let out = std::process::Command::new("git")
                    .args(["rev-parse", "--short=12", "HEAD"])
                    .current_dir(dir)
                    .stderr(std::process::Stdio::null())
                    .output()
                    .ok()?;
                out.status
                    .success()
                    .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
            })
            .clone()
    }

    /// Metadata every scan carries besides the plan and the instrument: optics, scene,
    /// script path and hash, git revision, program version.
    pub fn scan_meta(&self) -> Value {
        let script = self.script();
        json!({
            "optics": self.optics(),
            "scene": self.scene(),
            "script": {
                "path": script.path.map(|p| p.display().to_string()),
                "sha256": script.sha256,
                "repl_line": script.line,
            },
            "git_revision": self.git_revision(),
            "program": format!("bfpscope {}", env!("CARGO_PKG_VERSION")),
            "config": self.settings.config_path.as_ref().map(|p| p.display().to_string()),
            "protocol": self.protocol(),
            "notes": *lock(&self.notes),
        })
    }

    /// The innermost running protocol (#{name, args}) or null.
    pub fn protocol(&self) -> Value {
        lock(&self.protocols).last().cloned().unwrap_or(Value::Null)
    }

    /// What every file a script writes carries: program, script path and hash, git revision,
    /// the running protocol with its arguments, and the time written.
    pub fn provenance(&self) -> Value {
        let script = self.script();
        json!({
            "program": format!("bfpscope {}", env!("CARGO_PKG_VERSION")),
            "script": {
                "path": script.path.map(|p| p.display().to_string()),
                "sha256": script.sha256,
                "repl_line": script.line,
            },
            "git_revision": self.git_revision(),
            "protocol": self.protocol(),
            "written": crate::data::clock::utc_now(),
        })
    }
}

/// SHA-256 of some bytes as lowercase hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    let d = sha2::Sha256::digest(bytes);
    d.iter().map(|b| format!("{b:02x}")).collect()
}
