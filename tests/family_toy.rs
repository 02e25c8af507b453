//! A device family that lives only in the test tree: a toy stage and a toy QPD, registered
//! at run time through the same registry as the built-in families (`instrument::registry`),
//! then connected, moved, read and scanned through the ordinary bindings.

use bfpscope::instrument::registry::{self, Family, Open};
use bfpscope::instrument::{DeviceError, Instrument, Pos, Qpd, QpdReading, Stage, VirtualClock};
use bfpscope::script::{Settings, Workbench};
use std::sync::Arc;

/// Travel of every toy axis, µm.
const TRAVEL_UM: f64 = 20.0;

/// A perfect stage: it is where it was sent, at once.
struct ToyStage(Pos);

impl Stage for ToyStage {
    fn name(&self) -> String {
        "toy stage".into()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        Ok(self.0)
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.0 = target;
        Ok(())
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        Ok([(-TRAVEL_UM, TRAVEL_UM); 3])
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// A QPD whose signals are a closed form of the toy stage's position, which it shares:
/// Sx = x/10, Sy = −y/10, Sz = 1 (x, y in µm).
struct ToyQpd(Arc<std::sync::Mutex<Pos>>);

impl Qpd for ToyQpd {
    fn name(&self) -> String {
        "toy QPD".into()
    }
    fn sample_rate(&self) -> f64 {
        1000.0
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let p = *self.0.lock().unwrap();
        Ok(QpdReading {
            sx: p[0] / 10.0,
            sy: -p[1] / 10.0,
            sz: 1.0,
            n,
            ..QpdReading::default()
        })
    }
}

/// The stage and the QPD share the position through this wrapper.
struct SharedToyStage(Arc<std::sync::Mutex<Pos>>, ToyStage);

impl Stage for SharedToyStage {
    fn name(&self) -> String {
        self.1.name()
    }
    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.1.position()
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.1.move_to(target)?;
        *self.0.lock().unwrap() = target;
        Ok(())
    }
    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        self.1.travel_range()
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.1.stop()
    }
}

/// The toy family's opening: no options, the settle time `connect` gives.
fn open_toy(
    options: &serde_json::Map<String, serde_json::Value>,
    settle_s: f64,
) -> Result<Instrument, String> {
    if let Some(k) = options.keys().next() {
        return Err(format!("the toy family takes no option, got {k}"));
    }
    let at = Arc::new(std::sync::Mutex::new([0.0; 3]));
    Ok(Instrument {
        stage: Box::new(SharedToyStage(at.clone(), ToyStage([0.0; 3]))),
        qpd: Box::new(ToyQpd(at)),
        clock: Arc::new(VirtualClock::default()),
        settle_s,
        description: serde_json::json!({ "backend": "toy", "stage": "toy stage", "qpd": "toy QPD" }),
    })
}

/// The family's one line (a built-in family's line in `registry::FAMILIES`).
const TOY: Family = Family {
    stages: &["toy"],
    qpds: &["toy"],
    stage_defaults: registry::StageDefaults {
        poll_ms: 7,
        settle_s: Some(0.002),
    },
    help: registry::ConnectHelp {
        backend: "\"toy\" (a test's own family)",
        about: "",
    },
    ..Family::new("toy", "toy", Open::Build(open_toy))
};

fn workbench() -> Workbench {
    registry::register_family(TOY).expect("the toy family's names are new");
    let dir = std::env::temp_dir().join(format!("bfpscope-toy-{}", std::process::id()));
    let (s, _) = Settings::captured(&dir);
    Workbench::new(s)
}

fn eval(wb: &mut Workbench, code: &str) -> rhai::Dynamic {
    wb.eval_source("toy", code)
        .unwrap_or_else(|e| panic!("{code}: {e}"))
}

#[test]
fn a_family_registered_at_run_time_connects_moves_reads_and_scans() {
    let mut wb = workbench();
    let line = eval(&mut wb, "connect(#{backend: \"toy\"})").to_string();
    assert_eq!(line, "connected toy: toy stage, toy QPD");
    assert_eq!(eval(&mut wb, "status().backend").to_string(), "toy");
    let _ = eval(&mut wb, "mv(#{x: 1.5, y: -2.0})");
    assert_eq!(eval(&mut wb, "pos().x").as_float().unwrap(), 1.5);
    assert_eq!(eval(&mut wb, "pos().y").as_float().unwrap(), -2.0);
    // the read is the toy's closed form at the stage position
    let sx = eval(&mut wb, "qpd(10).sx").as_float().unwrap();
    assert!((sx - 0.15).abs() < 1e-12, "{sx}");
    // a relative scan through the scan engine: 5 points from x = 0.5 to 2.5, back to 1.5
    let a = eval(
        &mut wb,
        "let s = dscan(\"x\", -1, 1, 4, 0.001); [s.cols.to_float(), s.sx.at(0, 0), s.sx.at(0, 4), pos().x]",
    )
    .into_typed_array::<f64>()
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a[0], 5.0);
    assert!((a[1] - 0.05).abs() < 1e-12, "first pixel at x = 0.5: {a:?}");
    assert!((a[2] - 0.25).abs() < 1e-12, "last pixel at x = 2.5: {a:?}");
    assert_eq!(a[3], 1.5, "the relative scan returns to its start");
    // the soft limits narrowed to the toy's travel refuse a plan beyond it, before any move
    let e = wb
        .eval_source("toy", "ascan(\"x\", 0, 30, 3, 0.001)")
        .unwrap_err()
        .to_string();
    assert!(e.contains("30"), "{e}");
    assert_eq!(eval(&mut wb, "pos().x").as_float().unwrap(), 1.5);
}

#[test]
fn a_registered_family_is_listed_and_refuses_keys_it_does_not_take() {
    let mut wb = workbench();
    let e = wb
        .eval_source("toy", "connect(#{backend: \"hexapod\"})")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"toy\""),
        "the toy is among the available backends: {e}"
    );
    let e = wb
        .eval_source("toy", "connect(#{backend: \"toy\", qpd_port: \"/dev/x\"})")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(
            "connect: qpd_port applies to backend \"hardware\" / \"thorlabs\" only, not \"toy\""
        ),
        "{e}"
    );
}

#[test]
fn the_config_reads_a_registered_familys_backends_and_stage_defaults() {
    registry::register_family(TOY).expect("the toy family's names are new");
    let toml = "[stage]\nbackend = \"toy\"\n[qpd]\nbackend = \"toy\"\n";
    let cfg =
        bfpscope::config::Config::from_toml_str(toml, "toy.toml").unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(cfg.stage.backend.as_str(), "toy");
    assert_eq!(cfg.qpd.backend.as_str(), "toy");
    // the family's defaults, not the config's (5 ms poll, 5 ms settle)
    assert_eq!(cfg.stage.poll_ms(), 7);
    assert_eq!(cfg.stage.settle_s, 0.002);
    // a settle time the file gives is kept
    let cfg = bfpscope::config::Config::from_toml_str(
        "[stage]\nbackend = \"toy\"\nsettle_s = 0.01\npoll_ms = 3\n[qpd]\nbackend = \"toy\"\n",
        "toy.toml",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((cfg.stage.settle_s, cfg.stage.poll_ms()), (0.01, 3));
    // a name no family provides is refused with the list of those that are
    let e = bfpscope::config::Config::from_toml_str("[stage]\nbackend = \"hexapod\"\n", "toy.toml")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(
            "unknown variant `hexapod`, expected one of `sim`, `gcs`, `kpz101`, `madlib`, `toy`"
        ),
        "{e}"
    );
}
