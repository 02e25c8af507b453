//! Motion and reads: `pos`, `wa`, `mv`, `mvr`, `qpd`, `ct`, `status`, `connect`, `clock`,
//! `limits`, and the mock instrument's `mock_commands`. Every move goes through
//! `acquire::checked_move` (soft limits first).

use super::ctx::Ctx;
use super::registry::{fail, int, num, Doc, Opts, RResult, Registrar};
use crate::acquire::mock::{mock_instrument, MockConfig};
use crate::acquire::{checked_move, Axis};
use crate::instrument::{Pos, QpdReading};
use rhai::{Array, Dynamic, Map, INT};

/// `#{x, y, z}` in µm.
pub fn pos_map(p: Pos) -> Map {
    let mut m = Map::new();
    for a in Axis::ALL {
        m.insert(a.name().into(), p[a.index()].into());
    }
    m
}

fn reading_map(r: &QpdReading) -> Map {
    let mut m = Map::new();
    for (k, v) in [
        ("sx", r.sx),
        ("sy", r.sy),
        ("sz", r.sz),
        ("sx_std", r.sx_std),
        ("sy_std", r.sy_std),
        ("sz_std", r.sz_std),
    ] {
        m.insert(k.into(), v.into());
    }
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
        let mut target = inst.stage.position().map_err(|e| format!("{who}: {e}"))?;
        for i in 0..3 {
            if let Some(v) = t[i] {
                target[i] = if relative { target[i] + v } else { v };
            }
        }
        checked_move(inst, &limits, target, who).map_err(Into::into)
    })
}

pub fn register(r: &mut Registrar) {
    let ctx = r.ctx();
    let c = ctx.clone();
    r.bind(
        Doc::func("pos", "motion")
            .returns("map", "#{x, y, z} in µm")
            .summary("current stage position")
            .example("pos()", "#{x: 0.0, y: 0.0, z: 0.0}")
            .example("mv(#{x: 1.5}); pos().x", "1.5"),
        move || -> RResult<Map> {
            c.with_instrument("pos", |i| {
                Ok(pos_map(
                    i.stage.position().map_err(|e| format!("pos: {e}"))?,
                ))
            })
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("wa", "motion")
            .summary("where all: print the position of every axis")
            .help(
                "SPEC's `wa`. Prints `x = … µm  y = … µm  z = … µm`; use pos() to get the values.",
            )
            .example("wa()", "()"),
        move || -> RResult<()> {
            let p = c.with_instrument("wa", |i| {
                i.stage.position().map_err(|e| format!("wa: {e}").into())
            })?;
            c.print(&format!(
                "x = {:.4} µm   y = {:.4} µm   z = {:.4} µm",
                p[0], p[1], p[2]
            ));
            Ok(())
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("mv", "motion")
            .map("target", "absolute target, any subset of the axes", AXES_KEYS)
            .summary("move the stage to an absolute position (any subset of x, y, z)")
            .help(
                "The target is checked against the soft limits (config [safety] soft_limits, narrowed to the stage's \
                 travel range) before the move; a refused move moves nothing. Waits the settle time.",
            )
            .example("mv(#{x: 1.0, z: -0.5}); pos()", "#{x: 1.0, y: 0.0, z: -0.5}")
            .example("mv(#{x: 80.0})", "error: x = 80 µm is above the soft limit x ≤ 50 µm")
            .example("mv(#{w: 1.0})", "error: unknown axis `w`"),
        move |m: Map| do_move(&c, "mv", &m, false),
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("mvr", "motion")
            .map("step", "relative move, any subset of the axes", AXES_KEYS)
            .summary("move the stage relative to where it is")
            .example("mv(#{y: 1.0}); mvr(#{y: 0.25}); pos().y", "1.25"),
        move |m: Map| do_move(&c, "mvr", &m, true),
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("qpd", "reads")
            .arg("n", "int", "samples", "number of samples to average, 1 ≤ n ≤ 10000000")
            .returns("map", "#{sx, sy, sz, sx_std, sy_std, sz_std, n}: means and standard deviations (QPD signal units)")
            .summary("read the QPD: the mean of n samples of Sx, Sy, Sz")
            .example("mv(#{x: 0.2}); round(qpd(100).sx * 1e4) / 1e4", "0.1558")
            .example("qpd(0)", "error: qpd: n = 0 is out of range: 1 ≤ n ≤ 10000000"),
        move |n: Dynamic| -> RResult<Map> {
            let n = int("qpd", "n", &n)?;
            if !(1..=10_000_000).contains(&n) {
                return fail(format!("qpd: n = {n} is out of range: 1 ≤ n ≤ 10000000"));
            }
            c.with_instrument("qpd", |i| Ok(reading_map(&i.qpd.read(n as usize).map_err(|e| format!("qpd: {e}"))?)))
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("ct", "reads")
            .arg("seconds", "float", "s", "counting time, 0 < seconds ≤ 3600")
            .returns("map", "#{sx, sy, sz, sx_std, sy_std, sz_std, n, seconds}")
            .summary("count: read the QPD for a given time (SPEC's ct)")
            .help("Reads round(seconds × sample rate) samples (at least one).")
            .example("ct(0.01).n", "1000")
            .example(
                "ct(-1)",
                "error: ct: seconds = -1 is out of range: 0 < seconds ≤ 3600",
            ),
        move |t: Dynamic| -> RResult<Map> {
            let t = num("ct", "seconds", &t)?;
            if !(t > 0.0 && t <= 3600.0) {
                return fail(format!(
                    "ct: seconds = {t} is out of range: 0 < seconds ≤ 3600"
                ));
            }
            c.with_instrument("ct", |i| {
                let n = crate::acquire::engine::samples_per_point(t, i.qpd.sample_rate());
                let mut m = reading_map(&i.qpd.read(n).map_err(|e| format!("ct: {e}"))?);
                m.insert("seconds".into(), t.into());
                Ok(m)
            })
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("clock", "reads")
            .returns("float", "s")
            .summary(
                "instrument time: simulated seconds on a virtual clock, wall seconds on hardware",
            )
            .example("let t0 = clock(); ct(0.5); clock() - t0", "0.5"),
        move || -> RResult<f64> { c.with_instrument("clock", |i| Ok(i.clock.now())) },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("limits", "motion")
            .returns(
                "map",
                "#{x: [min, max], y: [...], z: [...], max_step_um} in µm",
            )
            .summary("the soft limits in force (config ∩ stage travel range)")
            .example("limits().x", "[-50.0, 50.0]"),
        move || -> RResult<Map> {
            let l = c.settings.limits;
            let l =
                if c.is_connected() {
                    c.with_instrument("limits", |i| {
                        Ok(l.within_travel(
                            i.stage.travel_range().map_err(|e| format!("limits: {e}"))?,
                        ))
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
            Ok(m)
        },
    );
    let c = ctx.clone();
    r.bind(
        Doc::func("status", "motion")
            .returns("map", "#{connected, instrument, position, clock_s, virtual_clock, limits, data_dir, last_scan}")
            .summary("what is connected, where the stage is, where scans go")
            .example("status().connected", "true")
            .example("status().position.x", "0.0"),
        move || -> RResult<Map> {
            let mut m = Map::new();
            m.insert("connected".into(), c.is_connected().into());
            m.insert("data_dir".into(), c.store.dir().display().to_string().into());
            m.insert("last_scan".into(), (c.store.last_number() as INT).into());
            m.insert("limits".into(), c.settings.limits.describe().into());
            if c.is_connected() {
                c.with_instrument("status", |i| {
                    m.insert("instrument".into(), super::types::json_to_dynamic(&i.description));
                    match i.stage.position() {
                        Ok(p) => m.insert("position".into(), pos_map(p).into()),
                        Err(e) => m.insert("position".into(), format!("unknown: {e}").into()),
                    };
                    m.insert("clock_s".into(), i.clock.now().into());
                    m.insert("virtual_clock".into(), i.clock.is_virtual().into());
                    Ok(())
                })?;
            }
            Ok(m)
        },
    );

    let d = Doc::func("connect", "motion")
        .map(
            "config",
            "which backend and its options",
            &[
                ("backend", "string", "", "\"mock\" (analytic test signal); \"sim\" and serial backends when they land"),
                ("settle", "float", "s", "optional: settle time per move (mock; default 0.001)"),
                ("rate", "float", "Hz", "optional: QPD sample rate (mock; default 100000)"),
                ("start", "map", "µm", "optional: initial position #{x, y, z} (mock)"),
                ("fail_move_after", "int", "", "optional: the stage disconnects on the move after this many (mock fault injection)"),
                ("fail_read_after", "int", "", "optional: the QPD times out on the read after this many (mock fault injection)"),
                ("abort_after_reads", "int", "", "optional: raise the Ctrl-C flag after this many reads (mock)"),
            ],
        )
        .returns("string", "description of the connected instrument")
        .summary("connect an instrument backend (replaces the current one)")
        .help(
            "The mock backend is for tests and examples: a noiseless analytic signal \
             sx = x·exp(-(x²+y²)/0.16)·exp(-z²/0.5), sy = 0.7·y·(same), sz = 1 - 0.1·(same), on a \
             virtual clock, travel x, y ±50 µm, z ±10 µm. It can be told to fail or to raise the \
             abort flag, to test the safety rules from scripts.",
        )
        .example("connect(#{backend: \"mock\", start: #{x: 2.0}}); pos().x", "2.0")
        .example("connect(#{backend: \"hexapod\"})", "error: backend = \"hexapod\" is not available");
    let spec = d.spec();
    let c = ctx.clone();
    r.bind(d, move |m: Map| -> RResult<String> {
        let o = Opts::new(&spec, &m)?;
        let backend = o.string("backend")?.unwrap_or_else(|| "mock".into());
        match backend.as_str() {
            "mock" => {
                let mut cfg = MockConfig::default();
                if let Some(s) = o.f64("settle")? {
                    if !(0.0..=10.0).contains(&s) {
                        return fail(format!(
                            "connect: settle = {s} is out of range: 0 ≤ settle ≤ 10 s"
                        ));
                    }
                    cfg.settle_s = s;
                }
                if let Some(r) = o.f64("rate")? {
                    if !(1.0..=1e9).contains(&r) {
                        return fail(format!(
                            "connect: rate = {r} is out of range: 1 ≤ rate ≤ 1e9 Hz"
                        ));
                    }
                    cfg.rate_hz = r;
                }
                if let Some(s) = m.get("start") {
                    let Some(sm) = s.read_lock::<Map>() else {
                        return fail("connect: start must be a map #{x, y, z} (µm)");
                    };
                    let t = axes_map("connect start", &sm)?;
                    for (st, v) in cfg.start.iter_mut().zip(t) {
                        *st = v.unwrap_or(0.0);
                    }
                }
                let count = |k: &str| -> RResult<Option<usize>> {
                    match o.int(k)? {
                        Some(v) if v < 0 => {
                            fail(format!("connect: {k} = {v} is out of range: {k} ≥ 0"))
                        }
                        v => Ok(v.map(|v| v as usize)),
                    }
                };
                cfg.fail_move_after = count("fail_move_after")?;
                cfg.fail_read_after = count("fail_read_after")?;
                cfg.abort_after_reads =
                    count("abort_after_reads")?.map(|k| (k, c.settings.abort.clone()));
                let (inst, h) = mock_instrument(cfg);
                let desc = inst.description.to_string();
                c.connect(inst, Some(h));
                Ok(format!("connected: {desc}"))
            }
            other => fail(format!(
                "connect: backend = {other:?} is not available; available: \"mock\" \
                 (the simulator and the serial drivers plug in here when they land)"
            )),
        }
    });

    let c = ctx.clone();
    r.bind(
        Doc::func("mock_commands", "mock")
            .returns(
                "array",
                "strings such as \"move 1 0 0\", \"read 100\", \"position?\"",
            )
            .summary("every command the mock instrument was sent (for tests of the safety rules)")
            .example(
                "mv(#{x: 1}); mock_commands().filter(|c| c.starts_with(\"move\"))",
                "[\"move 1 0 0\"]",
            ),
        move || -> RResult<Array> {
            match c.mock() {
                Some(h) => Ok(h.commands().into_iter().map(Dynamic::from).collect()),
                None => fail("mock_commands: the connected instrument is not the mock"),
            }
        },
    );
}
