//! The targeted protocols (stdlib/targeted.rhai) on the hardware backends beside the paper's
//! bench (tests/bench_drivers.rs): a PI E-727 stage with the Red Pitaya STEMlab digitiser, and
//! three Thorlabs KPZ101 piezo cubes with the KPA101 position aligner. Each driver talks to its
//! emulator (written from the vendor's document), and the emulators image a simulator scene at
//! the emulated stage position (`sim_signal_source`), so the protocol's answer is checked
//! against the scene by an independent path: the bead's position as placed, the reference
//! bead's weight (1 by definition) and its mass from ρ·πd³/6, a filament's linear density from
//! its diameter. Every reading goes through the one scan engine: autosaved, the pattern in the
//! metadata; a Ctrl-C or a device fault mid-protocol ends it with the device's words, the
//! stop, and the partial arm on disk.

use bfpscope::config::connect::{
    connect, connect_emulated_redpitaya, Connected, EmulatedStageLink,
};
use bfpscope::config::Config;
use bfpscope::data::{Scan, ScanStatus};
use bfpscope::instrument::emulator::{
    shared_position, sim_signal_source, start_kpa101_emulator, start_kpz101_stage_on, Emulator,
    KpaEmulatorConfig, LinkModel,
};
use bfpscope::instrument::sim::scene::{Bead, DiameterProfile, Filament, Scene};
use bfpscope::instrument::sim::{Renderer, SimConfig};
use bfpscope::instrument::{BufferedArm, BufferedTrace, DeviceError, Qpd, QpdReading};
use bfpscope::optics::params::{REF_BEAD_D_NM, REF_BEAD_N};
use bfpscope::optics::template::TemplateSpec;
use bfpscope::optics::{Optics, ValidOptics};
use bfpscope::script::{Settings, Workbench};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Where the scenes' bead sits, µm from the scene's origin (off the pixel lattice of any scan).
const BEAD_AT: [f64; 2] = [0.137, -0.071];
/// The Thorlabs cubes' 0–20 µm travel: the scene's origin at their middle.
const APT_CENTRE: [f64; 3] = [10.0, 10.0, 10.0];

/// The reference bead (110 nm polystyrene, n = 1.572) at `BEAD_AT`, z = 0.
fn bead_scene() -> Scene {
    let mut s = Scene::default();
    s.add_bead(Bead {
        pos: [BEAD_AT[0], BEAD_AT[1], 0.0],
        d_nm: REF_BEAD_D_NM,
        n: REF_BEAD_N,
    })
    .unwrap();
    s
}

/// The reference bead's mass, kDa: ρ·πd³/6 at 1.05 g/cm³ (polystyrene; the protocol's default
/// density), 6.02214076·10²³ Da/g.
fn ref_bead_mass_kda() -> f64 {
    let d_cm = REF_BEAD_D_NM * 1e-7;
    1.05 * std::f64::consts::PI / 6.0 * d_cm.powi(3) * 6.022_140_76e23 / 1e3
}

/// A workbench on `c` whose scans are autosaved to a fresh folder, and its Ctrl-C flag; with
/// `ctrl_c_at`, Ctrl-C is pressed during the QPD's n-th reading ([`CtrlCDuring`]).
fn workbench(
    tag: &str,
    mut c: Connected,
    ctrl_c_at: Option<usize>,
) -> (Workbench, PathBuf, Arc<AtomicBool>) {
    let dir = std::env::temp_dir().join(format!("bfpscope-thw-{tag}-{}", std::process::id()));
    crate::support::cleanup::at_exit(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    let (mut settings, _buf) = Settings::captured(&dir);
    settings.limits = c.limits;
    let abort = settings.abort.clone();
    if let Some(at) = ctrl_c_at {
        let inner = std::mem::replace(&mut c.instrument.qpd, Box::new(Unplugged));
        c.instrument.qpd = Box::new(CtrlCDuring {
            inner,
            reads: 0,
            at,
            abort: abort.clone(),
        });
    }
    let wb = Workbench::new(settings);
    assert_eq!(
        wb.ctx.optics(),
        optics(),
        "the scene is imaged in the session's optics"
    );
    wb.ctx.connect(c.instrument, None);
    (wb, dir, abort)
}

/// The session's optics (the default): the emulators image the scene in them.
fn optics() -> ValidOptics {
    ValidOptics::new(Optics::default()).unwrap()
}

fn renderer(scene: &Scene) -> Arc<Renderer> {
    Arc::new(Renderer::checked(&optics(), scene, TemplateSpec::default()).unwrap())
}

/// The scans autosaved in `dir`, in their numbers' order.
fn saved_in(dir: &Path) -> Vec<Scan> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| rd.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    paths.retain(|p| {
        p.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with("scan_") && n.ends_with(".npz"))
    });
    paths.sort();
    paths
        .iter()
        .map(|p| bfpscope::data::npz::load_scan(p).unwrap_or_else(|e| panic!("{e}")))
        .collect()
}

// ---- the Red Pitaya with a PI stage ----

/// The PI stage and the Red Pitaya emulators imaging `scene` (1 V per signal unit, `noise_v`
/// rms per ADC sample), connected through their drivers; a workbench on them.
struct RpBench {
    wb: Workbench,
    dir: PathBuf,
    abort: Arc<AtomicBool>,
    stage: Emulator,
    board: Emulator,
}

fn rp_bench(tag: &str, scene: &Scene, noise_v: f64, ctrl_c_at: Option<usize>) -> RpBench {
    let e = connect_emulated_redpitaya(
        renderer(scene),
        &SimConfig::default(),
        &Config::default(),
        noise_v,
        EmulatedStageLink::Pty,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let (wb, dir, abort) = workbench(tag, e.connected, ctrl_c_at);
    RpBench {
        wb,
        dir,
        abort,
        stage: e.stage,
        board: e.qpd,
    }
}

fn eval_map(wb: &mut Workbench, src: &str) -> rhai::Map {
    let r = wb.eval_source("t", src).unwrap_or_else(|e| panic!("{e}"));
    let m = r.read_lock::<rhai::Map>().unwrap().clone();
    m
}

fn f(m: &rhai::Map, k: &str) -> f64 {
    m[k].as_float().unwrap_or_else(|_| panic!("{k}: {}", m[k]))
}

fn bead_call(x: f64, y: f64, extra: &str) -> String {
    format!("import \"targeted\" as targeted; targeted::bead(#{{x: {x}, y: {y}{extra}}})")
}

/// The bead measured by the protocol is the scene's: position within 5 nm, weight 1 within 2 %
/// and within 4 of its stated 1σ, the mass ρ·πd³/6; every arm of every pass autosaved complete
/// with the pattern and why; n_points = 4 per pass.
fn check_bead_answer(m: &rhai::Map, at: [f64; 2], dir: &Path, backend: &str) {
    let passes = m["passes"].as_int().unwrap();
    println!(
        "{backend}: x {:.4} y {:.4} weight {:.4} ± {:.4} (CRLB {:.4}) mass {:.0} kDa, {passes} passes, {:.3} s, {}",
        f(m, "x"),
        f(m, "y"),
        f(m, "weight"),
        f(m, "weight_err"),
        f(m, "weight_crlb"),
        f(m, "mass_kda"),
        f(m, "instrument_s"),
        m["warnings"]
    );
    assert_eq!(
        m["status"].clone().into_string().unwrap(),
        "ok",
        "{}",
        m["warnings"]
    );
    assert!((f(m, "x") - at[0]).abs() < 0.005, "x {}", f(m, "x"));
    assert!((f(m, "y") - at[1]).abs() < 0.005, "y {}", f(m, "y"));
    let w = f(m, "weight");
    assert!((w - 1.0).abs() < 0.02, "weight {w}");
    assert!(
        (w - 1.0).abs() < 4.0 * f(m, "weight_err").max(1e-3),
        "weight {w} ± {}",
        f(m, "weight_err")
    );
    let mass = ref_bead_mass_kda();
    assert!(
        (f(m, "mass_kda") / (w * mass) - 1.0).abs() < 1e-3,
        "mass {} kDa vs weight × {mass}",
        f(m, "mass_kda")
    );
    assert_eq!(m["n_points"].as_int().unwrap(), 4 * passes);
    let saved = saved_in(dir);
    assert_eq!(saved.len() as i64, 2 * passes, "one scan per arm per pass");
    for s in &saved {
        assert_eq!(s.status, ScanStatus::Complete);
        let p = &s.meta["protocol"];
        assert_eq!(p["name"], "targeted::bead pattern", "{p}");
        assert!(
            p["args"]["why"].as_str().unwrap().contains("bead_design"),
            "{p}"
        );
        assert_eq!(p["args"]["points"].as_array().unwrap().len(), 4, "{p}");
        assert_eq!(s.sx.data.len(), 2);
        assert!(s.sx.data.iter().all(|v| v.is_finite()));
    }
}

/// targeted::bead through a PI stage and the Red Pitaya (point reads `ACQ:TRIG NOW` of the
/// dwell's window): the emulated bead's position, weight and mass, every arm autosaved with
/// its pattern, and the stage back where it started.
#[test]
fn targeted_bead_on_the_red_pitaya_recovers_the_emulated_bead() {
    let mut b = rp_bench("rp-bead", &bead_scene(), 0.01, None);
    let m = eval_map(
        &mut b.wb,
        &bead_call(BEAD_AT[0] + 0.03, BEAD_AT[1] - 0.02, ", dwell: 0.01"),
    );
    check_bead_answer(&m, BEAD_AT, &b.dir, "Red Pitaya");
    let saved = saved_in(&b.dir);
    assert_eq!(
        saved[0].meta["instrument"]["qpd"]["backend"], "redpitaya",
        "{}",
        saved[0].meta["instrument"]
    );
    // back where it started (the origin): the emulated stage's own position
    let p = b.stage.position();
    assert!(p[0].abs() < 1e-6 && p[1].abs() < 1e-6, "{p:?}");
    // one window per reading: ACQ:START once per point
    let starts = b
        .board
        .commands()
        .iter()
        .filter(|c| c.as_str() == "ACQ:START")
        .count() as i64;
    assert_eq!(
        starts,
        m["n_points"].as_int().unwrap(),
        "one acquisition per point"
    );
}

/// The board rejects the 6th acquisition (the second pass's second reading) with an error code:
/// the script stops with the board's words (device, command, code), the arm in progress is
/// saved failed with its partial data (the reading before), the board's acquisition is stopped,
/// no acquisition follows, and the stage ends at the arm's start (the pattern's centre).
#[test]
fn targeted_bead_stops_on_a_red_pitaya_error_with_the_board_words_and_the_partial_arm() {
    let mut b = rp_bench("rp-fault", &bead_scene(), 0.01, None);
    b.board.faults().reject = Some(("ACQ:START".into(), 5, -200));
    let e =
        b.wb.eval_source("t", &bead_call(BEAD_AT[0], BEAD_AT[1], ", dwell: 0.01"))
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("Red Pitaya on 127.0.0.1:")
            && e.contains("-200")
            && e.contains("ACQ:START")
            && e.contains("scan_line failed after 1 of 2 points"),
        "{e}"
    );
    let saved = saved_in(&b.dir);
    assert_eq!(
        saved.len(),
        3,
        "two arms of the first pass and the failed one: {e}"
    );
    let last = &saved[2];
    assert_eq!(last.status, ScanStatus::Failed, "{e}");
    assert_eq!(last.meta["protocol"]["name"], "targeted::bead pattern");
    assert_eq!(last.meta["protocol"]["args"]["pass"], 1);
    let v: Vec<f64> = last.sx.data.iter().copied().collect();
    assert!(v[0].is_finite() && v[1].is_nan(), "{v:?}");
    // the board: its acquisition stopped after the rejected start, no acquisition after that
    std::thread::sleep(Duration::from_millis(50));
    let log = b.board.commands();
    let i = log
        .iter()
        .enumerate()
        .filter(|(_, c)| c.as_str() == "ACQ:START")
        .map(|(i, _)| i)
        .nth(5)
        .unwrap_or_else(|| panic!("no 6th ACQ:START: {log:?}"));
    let after = &log[i + 1..];
    assert!(after.iter().any(|c| c == "ACQ:STOP"), "{after:?}");
    assert!(!after.iter().any(|c| c == "ACQ:START"), "{after:?}");
    // the stage: back to the arm's start (the pattern's centre), nothing else
    let centre = last.meta["protocol"]["args"]["centre"].as_array().unwrap();
    let p = b.stage.position();
    assert!(
        (p[0] - centre[0].as_f64().unwrap()).abs() < 1e-6
            && (p[1] - centre[1].as_f64().unwrap()).abs() < 1e-6,
        "{p:?} vs {centre:?}"
    );
}

/// A QPD that raises the Ctrl-C flag during its `n`-th reading (the user presses Ctrl-C while
/// the board acquires): every call goes to the real driver.
struct CtrlCDuring {
    inner: Box<dyn Qpd>,
    reads: usize,
    at: usize,
    abort: Arc<AtomicBool>,
}

impl CtrlCDuring {
    fn tick(&mut self) {
        self.reads += 1;
        if self.reads == self.at {
            self.abort.store(true, Ordering::SeqCst);
        }
    }
}

impl Qpd for CtrlCDuring {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn sample_rate(&self) -> f64 {
        self.inner.sample_rate()
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.tick();
        self.inner.read(n)
    }
    fn read_means(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.tick();
        self.inner.read_means(n)
    }
    fn read_for(&mut self, duration_s: f64) -> Result<QpdReading, DeviceError> {
        self.tick();
        self.inner.read_for(duration_s)
    }
    fn metadata(&self) -> Option<serde_json::Value> {
        self.inner.metadata()
    }
    fn input_range(&self) -> Option<bfpscope::instrument::range::InputRange> {
        self.inner.input_range()
    }
    fn arm_buffered(
        &mut self,
        n_samples: usize,
        sample_rate: f64,
        trigger: bfpscope::instrument::Trigger,
    ) -> Result<BufferedArm, DeviceError> {
        self.inner.arm_buffered(n_samples, sample_rate, trigger)
    }
    fn read_buffered(&mut self, timeout: Duration) -> Result<BufferedTrace, DeviceError> {
        self.inner.read_buffered(timeout)
    }
    fn stop_buffered(&mut self) -> Result<(), DeviceError> {
        self.inner.stop_buffered()
    }
    fn overhead_s(&self) -> f64 {
        self.inner.overhead_s()
    }
}

/// A QPD slot emptied while the real one is wrapped (never read).
struct Unplugged;

impl Qpd for Unplugged {
    fn name(&self) -> String {
        "none".into()
    }
    fn sample_rate(&self) -> f64 {
        1.0
    }
    fn read(&mut self, _: usize) -> Result<QpdReading, DeviceError> {
        unreachable!("the wrapped QPD's placeholder is never read")
    }
}

/// Ctrl-C during the 5th reading (the second pass's first point) on the Red Pitaya: the arm
/// ends aborted after that point, is saved (status aborted) with the point it took, the stage
/// returns to the arm's start, the script stops with the interruption in words, and no reading
/// is taken after it.
#[test]
fn ctrl_c_during_targeted_bead_on_the_red_pitaya_keeps_the_partial_arm() {
    let mut b = rp_bench("rp-ctrlc", &bead_scene(), 0.01, Some(5));
    let e =
        b.wb.eval_source("t", &bead_call(BEAD_AT[0], BEAD_AT[1], ", dwell: 0.01"))
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("scan_line aborted (Ctrl-C) after 1 of 2 points")
            && e.contains("partial scan (status aborted)"),
        "{e}"
    );
    assert!(
        !b.abort.load(Ordering::SeqCst),
        "the engine took the Ctrl-C"
    );
    let saved = saved_in(&b.dir);
    assert_eq!(
        saved.len(),
        3,
        "two arms of the first pass and the aborted one: {e}"
    );
    let last = &saved[2];
    assert_eq!(last.status, ScanStatus::Aborted);
    assert_eq!(last.meta["protocol"]["args"]["pass"], 1);
    let v: Vec<f64> = last.sx.data.iter().copied().collect();
    assert!(v[0].is_finite() && v[1].is_nan(), "{v:?}");
    let starts = b
        .board
        .commands()
        .iter()
        .filter(|c| c.as_str() == "ACQ:START")
        .count();
    assert_eq!(starts, 5, "no reading after the Ctrl-C");
    let centre = last.meta["protocol"]["args"]["centre"].as_array().unwrap();
    let p = b.stage.position();
    assert!(
        (p[0] - centre[0].as_f64().unwrap()).abs() < 1e-6
            && (p[1] - centre[1].as_f64().unwrap()).abs() < 1e-6,
        "{p:?} vs {centre:?}"
    );
}

// ---- a filament ----

/// A 13-protofilament microtubule (the protein cylinder of 13 × 13.75 MDa/µm, n = 1.587)
/// 8 µm long through `c`, 3° from the y axis.
fn microtubule_scene(c: [f64; 2]) -> (Scene, f64) {
    use bfpscope::analysis::quantities::{
        DA_PER_G, PROTEIN_DENSITY_G_CM3, PROTEIN_N, PROTOFILAMENT_MDA_PER_UM,
    };
    let mu = 13.0 * PROTOFILAMENT_MDA_PER_UM;
    let da_per_nm3 = PROTEIN_DENSITY_G_CM3 * 1e-21 * DA_PER_G;
    let d_nm = (4.0 * mu * 1e3 / da_per_nm3 / std::f64::consts::PI).sqrt();
    let t = 3f64.to_radians();
    let (dx, dy) = (4.0 * t.sin(), 4.0 * t.cos());
    let mut s = Scene::default();
    s.add_filament(Filament {
        points: vec![[c[0] - dx, c[1] - dy], [c[0] + dx, c[1] + dy]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm },
        n: PROTEIN_N,
        spacing_nm: 50.0,
    })
    .unwrap();
    (s, mu)
}

/// targeted::filament's answer against the scene: μ within 4 of its 1σ and 2 % of the truth,
/// the angle within 0.5° of 3°, and each strip autosaved complete with its plan and why.
fn check_filament_answer(m: &rhai::Map, mu: f64, dir: &Path, backend: &str) {
    println!(
        "{backend}: μ {:.2} ± {:.2} MDa/µm (CRLB {:.2}; true {mu:.2}), angle {:.2}° (CRLB {:.2}°), d {:.2} nm, {} strips, {:.3} s, {}",
        f(m, "mu_mda_um"),
        f(m, "mu_err_mda_um"),
        f(m, "mu_crlb_mda_um"),
        f(m, "angle_deg"),
        f(m, "angle_crlb_deg"),
        f(m, "diameter_nm"),
        m["n_strips"],
        f(m, "instrument_s"),
        m["warnings"]
    );
    assert_eq!(
        m["status"].clone().into_string().unwrap(),
        "ok",
        "{}",
        m["warnings"]
    );
    let got = f(m, "mu_mda_um");
    assert!(
        (got - mu).abs() < (4.0 * f(m, "mu_err_mda_um")).max(0.002 * mu)
            && (got / mu - 1.0).abs() < 0.02,
        "μ {got} ± {} vs {mu}",
        f(m, "mu_err_mda_um")
    );
    assert!(
        (f(m, "angle_deg") - 3.0).abs() < 4.0 * f(m, "angle_crlb_deg"),
        "angle {} (CRLB {})",
        f(m, "angle_deg"),
        f(m, "angle_crlb_deg")
    );
    let saved = saved_in(dir);
    let strips = m["n_strips"].as_int().unwrap() * m["passes"].as_int().unwrap();
    assert_eq!(saved.len() as i64, strips, "one scan per strip per pass");
    for s in &saved {
        assert_eq!(s.status, ScanStatus::Complete);
        let p = &s.meta["protocol"];
        assert_eq!(p["name"], "targeted::filament strip", "{p}");
        assert!(
            p["args"]["why"]
                .as_str()
                .unwrap()
                .contains("across the filament"),
            "{p}"
        );
        assert_eq!(s.sx.data.dim(), (10, 25), "{p}");
        assert!(s.sx.data.iter().all(|v| v.is_finite()));
    }
}

/// targeted::filament along 1 µm of the microtubule through `c` (two strips), 20 nm off its
/// axis, one pass (σ reached at once).
fn filament_call(c: [f64; 2]) -> String {
    let (s, co) = 3f64.to_radians().sin_cos();
    format!(
        "import \"targeted\" as targeted; targeted::filament(#{{from: [{}, {}], to: [{}, {}], dwell: 0.001, sigma_mda_um: 100.0}})",
        c[0] - 0.5 * s + 0.02,
        c[1] - 0.5 * co,
        c[0] + 0.5 * s + 0.02,
        c[1] + 0.5 * co
    )
}

/// targeted::filament through a PI stage and the Red Pitaya: two strips across a microtubule,
/// its linear density and angle as the scene holds them.
#[test]
fn targeted_filament_on_the_red_pitaya_recovers_the_emulated_microtubule() {
    let (scene, mu) = microtubule_scene([0.1, 0.0]);
    let mut b = rp_bench("rp-fil", &scene, 0.01, None);
    let m = eval_map(&mut b.wb, &filament_call([0.1, 0.0]));
    check_filament_answer(&m, mu, &b.dir, "Red Pitaya");
}

// ---- the Thorlabs cubes and aligner ----

/// The aligner's detector noise, V rms per reading (1.6 counts of XDiff: enough to dither the
/// ADC, whose count is 2.6 % of a 110 nm bead's peak XDiff at a 5 V Sum).
const APT_NOISE_V: f64 = 5e-4;

/// Three KPZ101 cubes (0–20 µm) and a KPA101 aligner on one stage position, the aligner
/// imaging `scene` with its origin at the cubes' centre; connected through the drivers.
struct AptBench {
    wb: Workbench,
    dir: PathBuf,
    cubes: [Emulator; 3],
    kpa: Emulator,
}

fn apt_bench(tag: &str, scene: &Scene, link: LinkModel, noise_v: f64) -> AptBench {
    let pos = shared_position(APT_CENTRE);
    let cubes = start_kpz101_stage_on([20.0; 3], pos.clone(), link).unwrap();
    let src = sim_signal_source(renderer(scene));
    let kpa = start_kpa101_emulator(
        KpaEmulatorConfig {
            link,
            noise_v,
            ..KpaEmulatorConfig::default()
        },
        pos,
        move |p: [f64; 3]| {
            src([
                p[0] - APT_CENTRE[0],
                p[1] - APT_CENTRE[1],
                p[2] - APT_CENTRE[2],
            ])
        },
    )
    .unwrap();
    let text = format!(
        "[stage]\nbackend = \"kpz101\"\nports = {{ x = \"{}\", y = \"{}\", z = \"{}\" }}\ntimeout_ms = 1000\npoll_ms = 1\n\
         settle_s = 0.0\ntolerance_um = 0.001\n\n[qpd]\nbackend = \"kpa101\"\nport = \"{}\"\ntimeout_ms = 1000\n\n[safety]\nmax_step_um = 2.0\n",
        cubes[0].path(),
        cubes[1].path(),
        cubes[2].path(),
        kpa.path()
    );
    let cfg = Config::from_toml_str(&text, "thorlabs.toml").unwrap();
    let c = connect(&cfg, |_| anyhow::bail!("not simulated")).unwrap_or_else(|e| panic!("{e}"));
    let (wb, dir, _) = workbench(tag, c, None);
    AptBench {
        wb,
        dir,
        cubes,
        kpa,
    }
}

/// targeted::bead through the KPZ101 cubes and the KPA101 aligner (Sx = XDiff/Sum, 16-bit
/// outputs and readings): the emulated bead's position, weight and mass, every arm autosaved
/// with its pattern, the cubes back where they started.
#[test]
fn targeted_bead_on_the_thorlabs_cubes_and_aligner_recovers_the_emulated_bead() {
    let mut b = apt_bench(
        "apt-bead",
        &bead_scene(),
        LinkModel::FULL_SPEED,
        APT_NOISE_V,
    );
    let at = [APT_CENTRE[0] + BEAD_AT[0], APT_CENTRE[1] + BEAD_AT[1]];
    let m = eval_map(
        &mut b.wb,
        &bead_call(at[0] + 0.03, at[1] - 0.02, ", dwell: 0.01"),
    );
    check_bead_answer(&m, at, &b.dir, "Thorlabs");
    let saved = saved_in(&b.dir);
    assert_eq!(
        saved[0].meta["instrument"]["qpd"]["backend"], "kpa101",
        "{}",
        saved[0].meta["instrument"]
    );
    // back where it started (the cubes' centre), to their 16-bit step (20 µm / 32767 = 0.6 nm)
    let p = b.kpa.position();
    assert!(
        (p[0] - APT_CENTRE[0]).abs() < 1e-3 && (p[1] - APT_CENTRE[1]).abs() < 1e-3,
        "{p:?}"
    );
    let _ = &b.cubes;
}

/// The aligner falls silent at the 6th reading (one reading per point: the dwell of 0.1 ms is
/// under one reading of the 115 200-baud link): the script stops with a timeout naming the
/// aligner and its request, the arm in progress is saved failed with the point it took and
/// returned to its start, and nothing is asked of the aligner after that.
#[test]
fn targeted_bead_stops_when_the_thorlabs_aligner_falls_silent() {
    let link = LinkModel {
        baud: Some(115_200),
        latency: Duration::ZERO,
    };
    let mut b = apt_bench("apt-fault", &bead_scene(), link, APT_NOISE_V);
    let at = [APT_CENTRE[0] + BEAD_AT[0], APT_CENTRE[1] + BEAD_AT[1]];
    let before = b.kpa.commands().len();
    b.kpa.faults().silent_after = Some(5);
    let e =
        b.wb.eval_source("t", &bead_call(at[0], at[1], ", dwell: 0.0001"))
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("Thorlabs KPA101")
            && e.contains("MGMSG_QUAD_REQ_PARAMS")
            && e.contains("scan_line failed after 1 of 2 points"),
        "{e}"
    );
    let saved = saved_in(&b.dir);
    assert_eq!(
        saved.len(),
        3,
        "two arms of the first pass and the failed one: {e}"
    );
    let last = &saved[2];
    assert_eq!(last.status, ScanStatus::Failed);
    assert_eq!(last.meta["protocol"]["args"]["pass"], 1);
    let v: Vec<f64> = last.sx.data.iter().copied().collect();
    assert!(v[0].is_finite() && v[1].is_nan(), "{v:?}");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(
        b.kpa.commands().len() - before,
        6,
        "six readings asked, none after the silent one: {:?}",
        &b.kpa.commands()[before..]
    );
    let centre = last.meta["protocol"]["args"]["centre"].as_array().unwrap();
    let p = b.kpa.position();
    assert!(
        (p[0] - centre[0].as_f64().unwrap()).abs() < 1e-3
            && (p[1] - centre[1].as_f64().unwrap()).abs() < 1e-3,
        "{p:?} vs {centre:?}"
    );
}

/// targeted::filament through the KPZ101 cubes and the KPA101 aligner: two strips across a
/// microtubule, its linear density and angle as the scene holds them.
#[test]
fn targeted_filament_on_the_thorlabs_cubes_and_aligner_recovers_the_emulated_microtubule() {
    let c = [APT_CENTRE[0] + 0.1, APT_CENTRE[1]];
    let (scene, mu) = microtubule_scene([0.1, 0.0]);
    let mut b = apt_bench("apt-fil", &scene, LinkModel::FULL_SPEED, APT_NOISE_V);
    let m = eval_map(&mut b.wb, &filament_call(c));
    check_filament_answer(&m, mu, &b.dir, "Thorlabs");
}
