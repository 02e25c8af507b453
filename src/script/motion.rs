//! Motion and reads: `pos`, `wa`, `mv`, `mvr`, `qpd`, `ct`, `status`, `connect`,
//! `disconnect`, `clock`, `limits`, and the mock instrument's `mock_commands`. Every move goes
//! through `acquire::checked_move` (soft limits first).
//!
//! Backends of `connect`: the device families of `instrument::registry` (their names, the keys
//! each takes, how each opens); this file checks the keys and opens what the family says.

use super::ctx::{Attached, Ctx};
use super::registry::{
    binding_list, fail, fields_map, int, non_negative, num, Doc, Opt, Opts, RResult, Registrar,
    Spec,
};
use super::scene::SceneRef;
use crate::acquire::{checked_move, Axis};
use crate::config::connect::{connect_emulated, connect_emulated_redpitaya, EmulatedStageLink};
use crate::config::{Config, MAX_BAUD, MAX_TIMEOUT_MS};
use crate::instrument::emulator::QpdEmulatorConfig;
use crate::instrument::mock::{mock_instrument, MockConfig, FAMILY as MOCK_FAMILY};
use crate::instrument::redpitaya::REDPITAYA;
use crate::instrument::registry::{self, BuildFn, Family, Open};
use crate::instrument::sim::scene::{Bead, Scene};
use crate::instrument::sim::{Renderer, SimConfig, SimCore};
use crate::instrument::{Instrument, Pos, QpdReading, VirtualClock};
use crate::optics::params::{REF_BEAD_D_NM, REF_BEAD_N};
use crate::optics::template::TemplateSpec;
use rhai::{Array, Dynamic, Map, INT};
use std::sync::Arc;

/// The options of this family's bindings, each key written once (`Opt`).
const ABORT_AFTER_READS: Opt = Opt::new("abort_after_reads", "int", "");
const BACKEND: Opt = Opt::new("backend", "string", "");
const BAUD: Opt = Opt::new("baud", "int", "baud");
const FAIL_MOVE_AFTER: Opt = Opt::new("fail_move_after", "int", "");
const FAIL_READ_AFTER: Opt = Opt::new("fail_read_after", "int", "");
const NOISE_V: Opt = Opt::new("noise_v", "float", "V");
const PACE: Opt = Opt::new("pace", "float", "");
const QPD_KEY: Opt = Opt::new("qpd", "string", "");
const QPD_BAUD: Opt = Opt::new("qpd_baud", "int", "baud");
const QPD_HOST: Opt = Opt::new("qpd_host", "string", "");
const QPD_PORT: Opt = Opt::new("qpd_port", "string", "");
const RATE: Opt = Opt::new("rate", "float", "Hz");
const SETTLE: Opt = Opt::new("settle", "float", "s");
const STAGE_BAUD: Opt = Opt::new("stage_baud", "int", "baud");
const STAGE_PORT: Opt = Opt::new("stage_port", "string", "");
const STAGE_PORTS: Opt = Opt::new("stage_ports", "map", "");
const TIMEOUT_MS: Opt = Opt::new("timeout_ms", "int", "ms");
const SCENE: Opt = Opt::new("scene", "Scene", "");
const START: Opt = Opt::new("start", "map", "µm");

/// `#{x, y, z}` in µm.
pub fn pos_map(p: Pos) -> Map {
    let mut m = Map::new();
    for a in Axis::ALL {
        m.insert(a.name().into(), p[a.index()].into());
    }
    m
}

fn reading_map(r: &QpdReading) -> Map {
    let mut m = fields_map!(r; sx, sy, sz, sx_std, sy_std, sz_std);
    m.insert("n".into(), (r.n as INT).into());
    m
}

/// Parse `#{x, y, z}` (any subset) into per-axis values, refusing other keys.
fn axes_map(who: &str, m: &Map) -> RResult<[Option<f64>; 3]> {
    let mut out = [None; 3];
    if m.is_empty() {
        return fail(format!(
            "{who}: give at least one axis, e.g. {who}(#{{x: 1.0}}) (µm)"
        ));
    }
    for (k, v) in m {
        let Some(a) = Axis::parse(k) else {
            return fail(format!(
                "{who}: unknown axis `{k}`; allowed keys: x, y, z (µm)"
            ));
        };
        out[a.index()] = Some(num(who, k, v)?);
    }
    Ok(out)
}

const AXES_KEYS: &[(&str, &str, &str, &str)] = &[
    ("x", "float", "µm", "optional: x target"),
    ("y", "float", "µm", "optional: y target"),
    ("z", "float", "µm", "optional: z target"),
];

fn do_move(ctx: &Ctx, who: &str, m: &Map, relative: bool) -> RResult<()> {
    let t = axes_map(who, m)?;
    let limits = ctx.settings.limits;
    ctx.with_instrument(who, |inst| {
        // from the last commanded target: axes not named keep theirs exactly
        let mut target = inst.stage.target().map_err(|e| format!("{who}: {e}"))?;
        for i in 0..3 {
            if let Some(v) = t[i] {
                target[i] = if relative { target[i] + v } else { v };
            }
        }
        checked_move(inst, &limits, target, who, &ctx.settings.abort).map_err(Into::into)
    })
}

binding_list! { pub fn register { bind_moves, bind_reads, bind_connect } }

/// Where the stage is and moving it: `pos`, `wa`, `mv`, `mvr`.
fn bind_moves(r: &mut Registrar) {
    let d = Doc::func("pos")
        .returns("map", "#{x, y, z} in µm")
        .summary("current stage position")
        .example("pos()", "#{x: 0.0, y: 0.0, z: 0.0}")
        .example("mv(#{x: 1.5}); pos().x", "1.5");
    r.bind_ctx(d, |c| move || pos(&c));

    let d = Doc::func("wa")
        .summary("where all: print the position of every axis")
        .help("SPEC's `wa`. Prints `x = … µm  y = … µm  z = … µm`; use pos() to get the values.")
        .example("wa()", "()");
    r.bind_ctx(d, |c| move || wa(&c));

    let d = Doc::func("mv")
        .map("target", "absolute target, any subset of the axes", AXES_KEYS)
        .summary("move the stage to an absolute position (any subset of x, y, z)")
        .help(
            "The target is checked against the soft limits (config [safety] soft_limits, narrowed to the stage's \
             travel range) before the move; a refused move moves nothing. Waits the settle time.",
        )
        .example("mv(#{x: 1.0, z: -0.5}); pos()", "#{x: 1.0, y: 0.0, z: -0.5}")
        .example("mv(#{x: 80.0})", "error: x = 80 µm is above the soft limit x ≤ 50 µm")
        .example("mv(#{w: 1.0})", "error: unknown axis `w`");
    r.bind_ctx(d, |c| move |m: Map| do_move(&c, "mv", &m, false));

    let d = Doc::func("mvr")
        .map("step", "relative move, any subset of the axes", AXES_KEYS)
        .summary("move the stage relative to where it is")
        .example("mv(#{y: 1.0}); mvr(#{y: 0.25}); pos().y", "1.25");
    r.bind_ctx(d, |c| move |m: Map| do_move(&c, "mvr", &m, true));
}

/// Reading the instrument: `qpd`, `ct`, `clock`, `limits`, `status`.
fn bind_reads(r: &mut Registrar) {
    let d = Doc::func("qpd")
        .arg("n", "int", "samples", &format!("number of samples to average, 1 ≤ n ≤ {QPD_MAX_SAMPLES}"))
        .returns("map", "#{sx, sy, sz, sx_std, sy_std, sz_std, n}: means and standard deviations (QPD signal units)")
        .summary("read the QPD: the mean of n samples of Sx, Sy, Sz")
        .example("mv(#{x: 0.2}); round(qpd(100).sx * 1e4) / 1e4", "0.1558")
        .example("qpd(0)", "error: qpd: n = 0 is out of range: 1 ≤ n ≤ 10000000");
    r.bind_ctx(d, |c| move |n: Dynamic| qpd(&c, &n));

    let d = Doc::func("ct")
        .arg(
            "seconds",
            "float",
            "s",
            &format!("counting time, 0 < seconds ≤ {CT_MAX_S}"),
        )
        .returns("map", "#{sx, sy, sz, sx_std, sy_std, sz_std, n, seconds}")
        .summary("count: read the QPD for a given time (SPEC's ct)")
        .help(
            "Reads n = round(seconds × sample rate) samples (at least one); `seconds` in the \
             result is the time actually counted, n / sample rate.",
        )
        .example("ct(0.01).n", "1000")
        .example("ct(0.0000123).seconds", "0.00001")
        .example(
            "ct(-1)",
            "error: ct: seconds = -1 is out of range: 0 < seconds ≤ 3600",
        );
    r.bind_ctx(d, |c| move |t: Dynamic| ct(&c, &t));

    let d = Doc::func("clock")
        .returns("float", "s")
        .summary("instrument time: simulated seconds on a virtual clock, wall seconds on hardware")
        .example("let t0 = clock(); ct(0.5); clock() - t0", "0.5");
    r.bind_ctx(d, |c| move || clock(&c));

    let d = Doc::func("limits")
        .returns(
            "map",
            "#{x: [min, max], y: [...], z: [...], max_step_um, max_speed_um_s} in µm and µm/s (max_speed_um_s is () without a speed limit)",
        )
        .summary("the safety rules in force: soft limits (config [safety] ∩ stage travel range), largest pixel pitch, speed limit")
        .example("limits().x", "[-50.0, 50.0]")
        .example("limits().max_step_um", "10.0")
        .example("limits().max_speed_um_s", "()");
    r.bind_ctx(d, |c| move || limits(&c));

    let d = Doc::func("status")
        .returns("map", "#{connected, backend, instrument, position, clock_s, virtual_clock, limits, data_dir, last_scan}")
        .summary("what is connected (backend, devices, ports), where the stage is, the safety rules, where scans go")
        .help("backend is \"mock\", \"sim\", \"hardware\" or \"emulated\" (() when nothing is connected); instrument is the connected instrument's description: device names, ports, baud rates, identification strings, travel range and limits for hardware.")
        .example("status().connected", "true")
        .example("status().backend", "\"mock\"")
        .example("status().limits", "\"x [-50, 50] µm, y [-50, 50] µm, z [-10, 10] µm; max step 10 µm; no speed limit\"")
        .example("status().position.x", "0.0");
    r.bind_ctx(d, |c| move || status(&c));
}

/// The families' parts of `connect`'s help (their backend entries or their sentences),
/// joined in the registry's order.
fn help_of(part: fn(&registry::ConnectHelp) -> &'static str, sep: &str) -> String {
    registry::families()
        .iter()
        .map(|f| part(&f.help))
        .filter(|s| !s.is_empty())
        .collect::<Vec<_>>()
        .join(sep)
}

/// `connect`, `disconnect`, `mock_commands`.
fn bind_connect(r: &mut Registrar) {
    let ctx = r.ctx();
    let (mock, emu) = (MockConfig::default(), QpdEmulatorConfig::default());
    let d = Doc::func("connect")
        .map(
            "config",
            "which backend and its options (all optional: connect() connects what the config names)",
            &[
                BACKEND.doc(format!("optional: \"config\" (default: what bfpscope.toml names, the simulator without one), {}", help_of(|h| h.backend, ", "))),
                STAGE_PORT.doc("optional: stage serial port, overrides [stage] port (hardware)".to_string()),
                QPD_PORT.doc("optional: QPD serial port, overrides [qpd] port (hardware, thorlabs)".to_string()),
                QPD_HOST.doc(format!("optional: the Red Pitaya's host name or address, overrides [qpd] host (redpitaya; TCP port from [qpd] port, default {})", crate::instrument::redpitaya::DEFAULT_PORT)),
                STAGE_PORTS.doc("optional: #{x, y, z} serial ports of the three KPZ101 cubes, overrides [stage] ports (thorlabs)".to_string()),
                BAUD.doc("optional: baud rate of both ports (hardware)".to_string()),
                STAGE_BAUD.doc("optional: stage baud rate (hardware)".to_string()),
                QPD_BAUD.doc("optional: QPD baud rate (hardware)".to_string()),
                TIMEOUT_MS.doc("optional: reply timeout of both devices (hardware)".to_string()),
                SCENE.doc("optional: what the simulator or the emulated QPD images (sim, emulated; default: the last simulate(scene), else empty for sim and a 110 nm polystyrene bead at the origin for emulated)".to_string()),
                NOISE_V.doc(format!("optional: emulated QPD noise per sample, rms (emulated; default {:e}, {} V per signal unit)", emu.noise_v[0], emu.volts_per_unit[0])),
                QPD_KEY.doc("optional: the emulated digitiser (emulated): \"scpi\" (default) or \"redpitaya\" (a Red Pitaya 4-input board over loopback TCP, its external trigger wired to the stage's OUT1, `[stage] trigger_line = 1`: scan_xy(#{..., mode: \"raster\"}) runs hardware-timed lines)".to_string()),
                SETTLE.doc(format!("optional: settle time per move (default [stage] settle_s; mock {})", mock.settle_s)),
                PACE.doc(format!("optional: wall seconds per simulated second (sim; default {}: as fast as it computes; 1: a real instrument's speed, to watch a scan build up in view())", VirtualClock::DEFAULT_PACE)),
                RATE.doc(format!("optional: QPD sample rate (mock; default {})", mock.rate_hz)),
                START.doc("optional: initial position #{x, y, z} (mock)".to_string()),
                FAIL_MOVE_AFTER.doc("optional: the stage disconnects on the move after this many (mock fault injection)".to_string()),
                FAIL_READ_AFTER.doc("optional: the QPD times out on the read after this many (mock fault injection)".to_string()),
                ABORT_AFTER_READS.doc("optional: raise the Ctrl-C flag after this many reads (mock)".to_string()),
            ],
        )
        .form("connect() -> string")
        .returns("string", "what was connected")
        .summary("connect an instrument backend (replaces and closes the current one)")
        .help(&format!(
            "connect() connects what bfpscope.toml names ([stage]/[qpd] backends and ports; the simulator without \
             a config), as `bfpscope repl|run|eval` do at start. {} The [safety] rules apply to every backend. \
             Errors name the backend and the device or port (docs/hardware.md).",
            help_of(|h| h.about, " ")
        ))
        .example("connect(#{backend: \"mock\", start: #{x: 2.0}}); pos().x", "2.0")
        .example("connect(#{backend: \"sim\"}); status().backend", "\"sim\"")
        .example("connect(#{backend: \"sim\", pace: -1.0})", "error: connect: pace = -1.0 is out of range")
        .example("connect(); status().instrument.stage", "\"simulated piezo stage\"")
        .example(
            "connect(#{backend: \"hardware\", stage_port: \"/dev/bfpscope-no-such-port\", qpd_port: \"/dev/bfpscope-no-such-qpd\"})",
            "error: connect: backend = \"hardware\": GCS stage on /dev/bfpscope-no-such-port: cannot open",
        )
        .example(
            "connect(#{backend: \"redpitaya\", stage_port: \"/dev/bfpscope-no-such-port\"})",
            "error: connect: backend = \"redpitaya\": config: qpd.host: required when backend = \"redpitaya\"",
        )
        .example(
            "connect(#{backend: \"gcs\"})",
            "error: connect: backend = \"gcs\": config: stage.port: required when backend = \"gcs\"",
        )
        .example("connect(#{backend: \"sim\", stage_port: \"/dev/ttyUSB0\"})", "error: connect: stage_port applies to backend \"hardware\"")
        .example("connect(#{backend: \"hexapod\"})", "error: backend = \"hexapod\" is not available");
    r.bind_map(d, connect);
    let c = ctx.clone();
    r.overload("connect", move || connect_default(&c));

    let d = Doc::func("disconnect")
        .returns("string", "what was disconnected")
        .summary("disconnect the instrument: close its ports (emulators stop); moves and reads then fail until connect()")
        .help("The stage is left where it is (servos stay on). Disconnecting twice is not an error.")
        .example("disconnect(); status().connected", "false")
        .example("disconnect()", "\"disconnected mock\"")
        .example("disconnect(); pos()", "error: pos: no instrument connected");
    r.bind_ctx(d, |c| move || disconnect(&c));

    let d = Doc::func("mock_commands")
        .returns(
            "array",
            "strings such as \"move 1 0 0\", \"read 100\", \"position?\"",
        )
        .summary("every command the mock instrument was sent (for tests of the safety rules)")
        .example(
            "mv(#{x: 1}); mock_commands().filter(|c| c.starts_with(\"move\"))",
            "[\"move 1 0 0\"]",
        );
    r.bind_ctx(d, |c| move || mock_commands(&c));
}

/// The largest sample count `qpd(n)` reads.
const QPD_MAX_SAMPLES: i64 = 10_000_000;
/// The longest counting time `ct(seconds)` accepts, in s.
const CT_MAX_S: f64 = 3600.0;

/// `pos()`: the stage position #{x, y, z} in µm.
fn pos(c: &Ctx) -> RResult<Map> {
    c.with_instrument("pos", |i| {
        Ok(pos_map(
            i.stage.position().map_err(|e| format!("pos: {e}"))?,
        ))
    })
}

/// `wa()`: print the position of every axis (µm).
fn wa(c: &Ctx) -> RResult<()> {
    let p = c.with_instrument("wa", |i| {
        i.stage.position().map_err(|e| format!("wa: {e}").into())
    })?;
    c.print(&format!(
        "x = {:.4} µm   y = {:.4} µm   z = {:.4} µm",
        p[0], p[1], p[2]
    ));
    Ok(())
}

/// `qpd(n)`: the mean and standard deviation of n QPD samples of Sx, Sy, Sz.
fn qpd(c: &Ctx, n: &Dynamic) -> RResult<Map> {
    let n = int("qpd", "n", n)?;
    if !(1..=QPD_MAX_SAMPLES).contains(&n) {
        return fail(format!(
            "qpd: n = {n} is out of range: 1 ≤ n ≤ {QPD_MAX_SAMPLES}"
        ));
    }
    c.with_instrument("qpd", |i| {
        Ok(reading_map(
            &i.qpd.read(n as usize).map_err(|e| format!("qpd: {e}"))?,
        ))
    })
}

/// `ct(seconds)`: read the QPD for n = round(seconds × sample rate) samples; `seconds` in the
/// result is n / sample rate, the time actually counted.
fn ct(c: &Ctx, t: &Dynamic) -> RResult<Map> {
    let t = num("ct", "seconds", t)?;
    if !(t > 0.0 && t <= CT_MAX_S) {
        return fail(format!(
            "ct: seconds = {t} is out of range: 0 < seconds ≤ {CT_MAX_S}"
        ));
    }
    c.with_instrument("ct", |i| {
        let rate = i.qpd.sample_rate();
        let n = crate::instrument::samples_per_point(t, rate);
        let mut m = reading_map(&i.qpd.read(n).map_err(|e| format!("ct: {e}"))?);
        m.insert("seconds".into(), (n as f64 / rate).into());
        Ok(m)
    })
}

/// `clock()`: the instrument's time in s (virtual on the simulator and mock).
fn clock(c: &Ctx) -> RResult<f64> {
    c.with_instrument("clock", |i| Ok(i.clock.now()))
}

/// `limits()`: the soft limits (narrowed to the stage's travel range when connected), the
/// largest step and the speed limit.
fn limits(c: &Ctx) -> RResult<Map> {
    let l = c.settings.limits;
    let l = if c.is_connected() {
        c.with_instrument("limits", |i| {
            Ok(
                l.within_travel(i.stage.travel_range().map_err(|e| format!("limits: {e}"))?)
                    .map_err(|e| format!("limits: {e}"))?,
            )
        })?
    } else {
        l
    };
    let mut m = Map::new();
    for a in Axis::ALL {
        let (lo, hi) = l.range[a.index()];
        m.insert(
            a.name().into(),
            Dynamic::from_array(vec![lo.into(), hi.into()]),
        );
    }
    m.insert("max_step_um".into(), l.max_step_um.into());
    m.insert(
        "max_speed_um_s".into(),
        l.max_speed_um_s.map_or(Dynamic::UNIT, Dynamic::from),
    );
    Ok(m)
}

/// `status()`: what is connected, where the stage is, the rules in force, where scans go.
fn status(c: &Ctx) -> RResult<Map> {
    let mut m = Map::new();
    m.insert("connected".into(), c.is_connected().into());
    m.insert(
        "backend".into(),
        c.backend().map_or(Dynamic::UNIT, Dynamic::from),
    );
    m.insert(
        "data_dir".into(),
        c.store.dir().display().to_string().into(),
    );
    m.insert("last_scan".into(), (c.store.last_number() as INT).into());
    m.insert("limits".into(), c.settings.limits.describe().into());
    if c.is_connected() {
        c.with_instrument("status", |i| {
            // the rules in force: soft limits narrowed to the travel range
            if let Ok(t) = i.stage.travel_range() {
                let l = c.settings.limits.within_travel(t);
                let text = l.map_or_else(|e| format!("refused: {e}"), |l| l.describe());
                m.insert("limits".into(), text.into());
            }
            m.insert(
                "instrument".into(),
                super::types::json_to_dynamic(&i.description),
            );
            match i.stage.position() {
                Ok(p) => m.insert("position".into(), pos_map(p).into()),
                Err(e) => m.insert("position".into(), format!("unknown: {e}").into()),
            };
            // the stage's own velocity setting (PI: VEL?), when it has one
            match i.stage.velocity() {
                // per axis, keys naming the unit (`x_um_s`): a bare `x` prints as µm
                Ok(Some(v)) => {
                    let mut vm = Map::new();
                    for a in Axis::ALL {
                        vm.insert(format!("{}_um_s", a.name()).into(), v[a.index()].into());
                    }
                    m.insert("velocity_um_s".into(), vm.into())
                }
                Ok(None) => None,
                Err(e) => m.insert("velocity_um_s".into(), format!("unknown: {e}").into()),
            };
            m.insert("clock_s".into(), i.clock.now().into());
            m.insert("virtual_clock".into(), i.clock.is_virtual().into());
            Ok(())
        })?;
    }
    Ok(m)
}

/// `connect(#{...})`: check the keys, then connect the backend ([`connect_binding`]).
/// A `connect` option that counts something (baud, milliseconds): an integer 1 ≤ k ≤ max, or
/// absent.
fn connect_count(o: &Opts, k: Opt, max: i64) -> RResult<Option<i64>> {
    let k = k.name;
    match o.int(k)? {
        Some(v) if !(1..=max).contains(&v) => fail(format!(
            "connect: {k} = {v} is out of range: 1 ≤ {k} ≤ {max}"
        )),
        v => Ok(v),
    }
}

fn connect(c: &Ctx, spec: &Spec, m: &Map) -> RResult<String> {
    let o = Opts::new(spec, m)?;
    connect_binding(c, &o, m)
}

/// `connect()`: connect what the config names ([`connect_config`]).
fn connect_default(c: &Ctx) -> RResult<String> {
    let cfg = base_config(c)?;
    connect_config(c, &cfg).map_err(Into::into)
}

/// `disconnect()`: close the instrument's ports; says what was connected.
fn disconnect(c: &Ctx) -> String {
    match c.disconnect() {
        Some(b) => format!("disconnected {b}"),
        None => "nothing was connected".into(),
    }
}

/// `mock_commands()`: every command the mock instrument was sent.
fn mock_commands(c: &Ctx) -> RResult<Array> {
    match c.mock() {
        Some(h) => Ok(h.commands().into_iter().map(Dynamic::from).collect()),
        None => fail("mock_commands: the connected instrument is not the mock"),
    }
}

/// The config in force for this workbench (the file given at start-up), or the defaults.
fn base_config(ctx: &Ctx) -> RResult<Config> {
    Ok(ctx.settings.config.clone().unwrap_or_default())
}

/// The backend an instrument's description names (`"hardware"`, `"emulated"`).
fn description_backend(inst: &Instrument) -> String {
    inst.description["backend"]
        .as_str()
        .unwrap_or_default()
        .to_string()
}

/// One line naming what is connected: `hardware: PI E-727 on /dev/ttyUSB0, QPD … on …`.
/// The connect's warnings (a strain gauge not zeroed) are said to the operator at once
/// ([`say_connect_warnings`]: stderr and the session log), at the prompt as in `run`/`eval`.
fn connected_line(ctx: &Ctx, backend: &str, inst: &Instrument) -> String {
    say_connect_warnings(ctx, &inst.description);
    format!(
        "connected {backend}: {}, {}",
        inst.stage.name(),
        inst.qpd.name()
    )
}

/// Say every warning a connect recorded (`instrument.warnings`: a KPZ101 strain gauge not
/// zeroed, …) to the operator, one line each, `WARNING: connect: …`, on stderr and in the
/// session log: the same words whether the connect was `connect()` at the prompt or the
/// config's connect at the start of `bfpscope repl|run|eval`. Returns the lines said.
pub fn say_connect_warnings(ctx: &Ctx, description: &serde_json::Value) -> Vec<String> {
    let lines: Vec<String> = description["warnings"]
        .as_array()
        .map(|w| {
            w.iter()
                .filter_map(|w| w.as_str())
                .map(|w| format!("WARNING: connect: {w}"))
                .collect()
        })
        .unwrap_or_default();
    for l in &lines {
        ctx.log_lasting(l);
    }
    lines
}

/// The scene for the simulator (`fallback` when no scene was given and the connected
/// instrument images none).
fn scene_for(ctx: &Ctx, m: &Map, fallback: impl FnOnce() -> Scene) -> RResult<Scene> {
    if let Some(v) = m.get(SCENE.name) {
        return match v.clone().try_cast::<SceneRef>() {
            Some(s) => Ok(s.0),
            None => fail(format!(
                "connect: scene must be a Scene (from scene()), got {}",
                v.type_name()
            )),
        };
    }
    Ok(ctx.scene().unwrap_or_else(fallback))
}

/// The scene `bfpscope emulate` and the emulated backend image by default: the paper's
/// reference bead (110 nm polystyrene, n = 1.572) at the origin.
pub fn reference_bead_scene() -> Scene {
    let mut s = Scene::default();
    let _ = s.add_bead(Bead {
        pos: [0.0; 3],
        d_nm: REF_BEAD_D_NM,
        n: REF_BEAD_N,
    });
    s
}

/// Connect the simulated instrument imaging `scene`.
fn connect_sim(ctx: &Ctx, scene: &Scene, settle_s: f64, pace: f64) -> Result<String, String> {
    let core = SimCore::new(&ctx.optics(), scene, SimConfig::default())
        .map_err(|e| format!("connect: backend = \"sim\": {e}"))?;
    core.clock.set_pace(pace);
    let line = connected_line(
        ctx,
        crate::instrument::sim::FAMILY.backend,
        &core.instrument(settle_s),
    );
    ctx.attach_sim(core, settle_s);
    Ok(line)
}

/// Connect what `cfg` names: the simulated instrument (empty scene) or the serial drivers.
/// Used by `connect()` and by `bfpscope repl|run|eval` at start.
pub fn connect_config(ctx: &Ctx, cfg: &Config) -> Result<String, String> {
    if cfg.is_simulated() {
        return connect_sim(ctx, &Scene::default(), cfg.stage.settle_s, 0.0);
    }
    connect_hardware(ctx, cfg, "config")
}

fn connect_hardware(ctx: &Ctx, cfg: &Config, name: &str) -> Result<String, String> {
    // Reconnecting to a port the connected instrument holds (drivers open ports exclusively):
    // close that connection first. Otherwise the current instrument stays until the new one
    // is up, so a failed connect leaves it alone.
    // (a Red Pitaya by its address: its SCPI server serves one client at a time)
    let rp_address = (cfg.qpd.backend == REDPITAYA)
        .then(|| {
            let port = crate::instrument::redpitaya::config::port(&cfg.qpd).ok()?;
            Some(format!("{}:{port}", cfg.qpd.host.as_deref()?))
        })
        .flatten();
    let wanted = [cfg.stage.port.clone(), cfg.qpd.port.clone(), rp_address];
    let held = ctx
        .with_instrument("connect", |i| {
            let d = &i.description;
            Ok(
                [&d["stage"]["port"], &d["qpd"]["port"], &d["qpd"]["address"]]
                    .iter()
                    .filter_map(|v| v.as_str().map(String::from))
                    .collect::<Vec<_>>(),
            )
        })
        .unwrap_or_default();
    if wanted.iter().flatten().any(|p| held.contains(p)) {
        ctx.disconnect();
    }
    let c = crate::config::connect::connect(cfg, |_| {
        Err(anyhow::anyhow!(
            "a hardware config does not build the simulator"
        ))
    })
    .map_err(|e| format!("connect: backend = {name:?}: {e}"))?;
    let backend = description_backend(&c.instrument);
    let line = connected_line(ctx, &backend, &c.instrument);
    ctx.attach(&backend, c.instrument, Attached::default());
    Ok(line)
}

/// `connect(#{backend, …})`: the family the backend names (`instrument::registry`), its keys
/// checked, then opened as the family says ([`Open`]).
fn connect_binding(c: &Ctx, o: &Opts, m: &Map) -> RResult<String> {
    let backend = o.string(BACKEND)?.unwrap_or_else(|| "config".into());
    let mut cfg = base_config(c)?;
    // "config" keeps the config's own backends (a GCS stage may read a KPA101, say) and
    // checks the keys against the family of the config's stage
    let from_config = backend == "config";
    let family = if from_config {
        registry::by_stage(cfg.stage.backend.as_str())
    } else {
        registry::by_backend(&backend)
    };
    let Some(family) = family else {
        return fail(format!(
            "connect: backend = {backend:?} is not available; available: {}",
            registry::available()
        ));
    };
    check_family_keys(&family, &backend, m)?;
    let settle = match o.f64(SETTLE)? {
        Some(s) if !(0.0..=10.0).contains(&s) => {
            return fail(format!(
                "connect: settle = {s} is out of range: 0 ≤ settle ≤ 10 s"
            ))
        }
        s => s,
    };
    if let Some(s) = settle {
        cfg.stage.settle_s = s;
    }
    match family.open {
        Open::Sim => open_sim(c, o, m, &cfg),
        Open::Config { stage, qpd } => {
            if !from_config {
                cfg.stage.backend = config_backend(stage)?;
                cfg.qpd.backend = config_backend(qpd)?;
            }
            apply_port_keys(o, &mut cfg)?;
            connect_hardware(c, &cfg, &backend).map_err(Into::into)
        }
        Open::Emulated => open_emulated(c, o, m, &cfg),
        Open::Mock => open_mock(c, o, m, settle),
        Open::Build(build) => open_built(c, &family, build, m, cfg.stage.settle_s),
    }
}

/// Refuse a key none of the families answering to `family.backend` takes, naming the
/// backends it applies to.
fn check_family_keys(family: &Family, backend: &str, m: &Map) -> RResult<()> {
    let takes = |k: &str| {
        registry::families()
            .iter()
            .any(|f| f.backend == family.backend && f.keys.contains(&k))
    };
    for k in registry::all_keys() {
        if m.contains_key(k) && !takes(k) {
            return fail(format!(
                "connect: {k} applies to backend {} only, not {backend:?}",
                registry::backends_taking(k)
                    .iter()
                    .map(|b| format!("\"{b}\""))
                    .collect::<Vec<_>>()
                    .join(" / ")
            ));
        }
    }
    Ok(())
}

/// A `[stage]`/`[qpd]` backend a family names, as the config's.
fn config_backend(name: &str) -> RResult<crate::config::Backend> {
    registry::config_backend(name).map_or_else(
        || fail(format!("connect: the config has no backend {name:?}")),
        Ok,
    )
}

/// The port, host, baud and timeout keys of `connect`'s map over the config's (only the
/// keys the family's backend takes get here).
fn apply_port_keys(o: &Opts, cfg: &mut Config) -> RResult<()> {
    if let Some(h) = o.string(QPD_HOST)? {
        if cfg.qpd.backend != REDPITAYA {
            return fail(format!(
                "connect: qpd_host applies to a Red Pitaya QPD (backend \"redpitaya\"), not {:?}",
                cfg.qpd.backend.as_str()
            ));
        }
        cfg.qpd.host = Some(h);
    }
    if let Some(p) = o.string(STAGE_PORT)? {
        // one controller on this port, in place of the config's port(s)
        cfg.stage.port = Some(p);
        cfg.stage.ports = None;
    }
    if let Some([x, y, z]) = o.axis_strings(STAGE_PORTS)? {
        cfg.stage.port = None;
        cfg.stage.ports = Some(crate::config::AxisPorts { x, y, z });
    }
    if let Some(p) = o.string(QPD_PORT)? {
        cfg.qpd.port = Some(p);
    }
    let positive = |k: Opt, max: i64| connect_count(o, k, max);
    if let Some(b) = positive(BAUD, MAX_BAUD.into())? {
        cfg.stage.baud = b as u32;
        cfg.qpd.baud = b as u32;
    }
    if let Some(b) = positive(STAGE_BAUD, MAX_BAUD.into())? {
        cfg.stage.baud = b as u32;
    }
    if let Some(b) = positive(QPD_BAUD, MAX_BAUD.into())? {
        cfg.qpd.baud = b as u32;
    }
    if let Some(t) = positive(TIMEOUT_MS, MAX_TIMEOUT_MS as i64)? {
        cfg.stage.timeout_ms = t as u64;
        cfg.qpd.timeout_ms = t as u64;
    }
    Ok(())
}

/// `connect(#{backend: "sim", scene, pace})`.
fn open_sim(c: &Ctx, o: &Opts, m: &Map, cfg: &Config) -> RResult<String> {
    let scene = scene_for(c, m, Scene::default)?;
    let pace = match o.f64(PACE)? {
        Some(p) if !(0.0..=100.0).contains(&p) => {
            return fail(format!(
                "connect: pace = {p:?} is out of range: 0 ≤ pace ≤ 100 wall seconds per simulated second"
            ))
        }
        p => p.unwrap_or(VirtualClock::DEFAULT_PACE),
    };
    connect_sim(c, &scene, cfg.stage.settle_s, pace).map_err(Into::into)
}

/// `connect(#{backend: "emulated", scene, noise_v, qpd})`.
fn open_emulated(c: &Ctx, o: &Opts, m: &Map, cfg: &Config) -> RResult<String> {
    let scene = scene_for(c, m, reference_bead_scene)?;
    let noise_v = o
        .f64(NOISE_V)?
        .unwrap_or(QpdEmulatorConfig::default().noise_v[0]);
    if !(0.0..=10.0).contains(&noise_v) {
        return fail(format!(
            "connect: noise_v = {noise_v} is out of range: 0 ≤ noise_v ≤ 10 V"
        ));
    }
    let sim = SimConfig::default();
    let renderer = Arc::new(
        Renderer::checked(&c.optics(), &scene, TemplateSpec::default())
            .map_err(|e| format!("connect: backend = \"emulated\": {e}"))?,
    );
    let e = match o.string(QPD_KEY)?.as_deref() {
        None | Some("scpi") => connect_emulated(renderer.clone(), &sim, cfg, noise_v),
        Some("redpitaya") => connect_emulated_redpitaya(
            renderer.clone(),
            &sim,
            cfg,
            noise_v,
            EmulatedStageLink::Pty,
        ),
        Some(other) => {
            return fail(format!(
                "connect: qpd = {other:?} is not an emulated digitiser; allowed: \"scpi\" (default), \"redpitaya\""
            ))
        }
    }
    .map_err(|e| format!("connect: backend = \"emulated\": {e}"))?;
    let backend = description_backend(&e.connected.instrument);
    let line = format!(
        "{} (emulators on {} and {})",
        connected_line(c, &backend, &e.connected.instrument),
        e.stage.path(),
        e.qpd.path()
    );
    c.attach(
        &backend,
        e.connected.instrument,
        Attached {
            keepalive: Some(Box::new((e.stage, e.qpd))),
            renderer: Some(renderer),
            ..Attached::default()
        },
    );
    Ok(line)
}

/// `connect(#{backend: "mock", rate, start, fail_move_after, fail_read_after,
/// abort_after_reads})`.
fn open_mock(c: &Ctx, o: &Opts, m: &Map, settle: Option<f64>) -> RResult<String> {
    let mut cfg = MockConfig::default();
    if let Some(s) = settle {
        cfg.settle_s = s;
    }
    if let Some(r) = o.f64(RATE)? {
        if !(1.0..=1e9).contains(&r) {
            return fail(format!(
                "connect: rate = {r} is out of range: 1 ≤ rate ≤ 1e9 Hz"
            ));
        }
        cfg.rate_hz = r;
    }
    if let Some(s) = m.get(START.name) {
        let Some(sm) = s.read_lock::<Map>() else {
            return fail("connect: start must be a map #{x, y, z} (µm)");
        };
        let t = axes_map("connect start", &sm)?;
        for (st, v) in cfg.start.iter_mut().zip(t) {
            *st = v.unwrap_or(0.0);
        }
    }
    let count = |k: Opt| -> RResult<Option<usize>> {
        o.int(k)?
            .map(|v| non_negative("connect", k.name, v).map(|n| n as usize))
            .transpose()
    };
    cfg.fail_move_after = count(FAIL_MOVE_AFTER)?;
    cfg.fail_read_after = count(FAIL_READ_AFTER)?;
    cfg.abort_after_reads = count(ABORT_AFTER_READS)?.map(|k| (k, c.settings.abort.clone()));
    let (inst, h) = mock_instrument(cfg);
    let backend = MOCK_FAMILY.backend;
    let line = connected_line(c, backend, &inst);
    c.attach(
        backend,
        inst,
        Attached {
            mock: Some(h),
            ..Attached::default()
        },
    );
    Ok(line)
}

/// A family that builds its own instrument from `connect`'s options ([`Open::Build`]).
fn open_built(c: &Ctx, family: &Family, build: BuildFn, m: &Map, settle_s: f64) -> RResult<String> {
    let mut options = serde_json::Map::new();
    for (k, v) in m
        .iter()
        .filter(|(k, _)| !["backend", "settle"].contains(&k.as_str()))
    {
        options.insert(k.to_string(), super::types::dynamic_to_json(v));
    }
    let inst = build(&options, settle_s)
        .map_err(|e| format!("connect: backend = {:?}: {e}", family.backend))?;
    let line = connected_line(c, family.backend, &inst);
    c.attach(family.backend, inst, Attached::default());
    Ok(line)
}
