//! Hardware-timed raster lines on the emulated hardware: a PI GCS stage emulator
//! whose trigger output OUT1 is wired to a Red Pitaya emulator's external trigger, spoken to by
//! the real drivers (GCS over a pseudo-terminal, the board over loopback TCP).
//!
//! - the stage's line capabilities as the controller reports them (`SPA?`, `WMS?`), with the
//!   config's values for a controller that does not answer;
//! - the board samples the moving stage: a triggered buffer taken during a line holds, sample
//!   by sample, the signal at the position the data recorder measured at that time.

use bfpscope::instrument::emulator::{
    shared_position, start_redpitaya_emulator, start_stage_emulator, Emulator,
    RedPitayaEmulatorConfig, StageEmulatorConfig, StagePath, WaveConfig,
};
use bfpscope::instrument::gcs::{GcsOptions, GcsStage, LineSweep};
use bfpscope::instrument::redpitaya::{ChannelMap, RedPitaya, RedPitayaOptions};
use bfpscope::instrument::scpi::Calibration;
use bfpscope::instrument::{LineScan, Qpd, Stage, Trigger};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

const DT: f64 = 50e-6;
const TAU: f64 = 0.5e-3;

fn gcs_opts() -> GcsOptions {
    GcsOptions {
        timeout: Duration::from_millis(300),
        on_target_timeout: Duration::from_millis(1000),
        poll_interval: Duration::from_millis(1),
        trigger_line: Some(1),
        ..GcsOptions::default()
    }
}

fn stage(wave: WaveConfig, opts: GcsOptions) -> (Emulator, GcsStage) {
    let cfg = StageEmulatorConfig {
        start: [10.0, 10.0, 5.0],
        settle_s: 0.002,
        wave,
        ..StageEmulatorConfig::default()
    };
    let e = start_stage_emulator(cfg, shared_position([0.0; 3])).unwrap();
    let s = GcsStage::open(e.path(), 115_200, opts).unwrap();
    (e, s)
}

#[test]
fn line_timing_is_what_the_controller_reports() {
    let (e, mut s) = stage(
        WaveConfig {
            servo_cycle_s: 40e-6,
            table_points: 8192,
            record_tables: 4,
            record_points: 2048,
            ..WaveConfig::default()
        },
        gcs_opts(),
    );
    let t = LineScan::line_timing(&mut s).unwrap().unwrap();
    assert_eq!(t.servo_cycle_s, 40e-6);
    assert_eq!(t.max_wave_points, 8192);
    // 0x16000200 answers 4 · 2048 points for all tables, 0x16000300 four tables
    assert_eq!(t.max_record_points, 2048);
    assert_eq!(t.trigger_line, Some(1));
    let log = e.commands();
    for q in [
        "SPA? 1 0x0E000200",
        "WMS? 1",
        "SPA? 1 0x16000200",
        "SPA? 1 0x16000300",
    ] {
        assert!(log.iter().any(|c| c == q), "{q} not sent: {log:?}");
    }
    // read once per connection
    let n = e.commands().len();
    assert_eq!(LineScan::line_timing(&mut s).unwrap().unwrap(), t);
    assert_eq!(e.commands().len(), n);
}

#[test]
fn a_controller_without_the_servo_parameter_uses_the_config_or_names_the_key() {
    // the controller rejects `SPA? 1 0x0E000200` with error 54 (unknown parameter)
    let (e, mut s) = stage(WaveConfig::default(), gcs_opts());
    e.faults().error_next = Some(54);
    let err = LineScan::line_timing(&mut s).unwrap_err().to_string();
    assert!(
        err.contains("SPA? 1 0x0E000200")
            && err.contains("54")
            && err.contains("[stage] servo_cycle_s"),
        "{err}"
    );
    let (e, mut s) = stage(
        WaveConfig::default(),
        GcsOptions {
            servo_cycle_s: Some(100e-6),
            ..gcs_opts()
        },
    );
    e.faults().error_next = Some(54);
    let t = LineScan::line_timing(&mut s).unwrap().unwrap();
    assert_eq!(t.servo_cycle_s, 100e-6);
    assert_eq!(t.max_wave_points, 65_536);
}

/// The board's signal: linear in x and y, so every sample names the position it was taken at.
fn linear(p: [f64; 3]) -> [f64; 3] {
    [0.05 * (p[0] - 15.0), 0.02 * (p[1] - 5.0), 0.2]
}

#[test]
fn the_board_samples_the_moving_stage_at_the_recorders_positions() {
    let pos = shared_position([10.0, 10.0, 5.0]);
    let path = StagePath::new();
    let (rp_emu, ext) = start_redpitaya_emulator(
        RedPitayaEmulatorConfig {
            noise_v: 0.0,
            path: Some(path.clone()),
            ..RedPitayaEmulatorConfig::default()
        },
        pos.clone(),
        linear,
        "127.0.0.1:0",
    )
    .unwrap();
    let cfg = StageEmulatorConfig {
        start: [10.0, 10.0, 5.0],
        settle_s: 0.002,
        wave: WaveConfig {
            servo_cycle_s: DT,
            lag_s: TAU,
            trigger_out: [Some(ext.clone()), None, None],
            path: Some(path),
            ..WaveConfig::default()
        },
        ..StageEmulatorConfig::default()
    };
    let stage_emu = start_stage_emulator(cfg, pos).unwrap();
    let mut s = GcsStage::open(stage_emu.path(), 115_200, gcs_opts()).unwrap();
    let hp = rp_emu.path().trim_start_matches("tcp://").to_string();
    let (h, p) = hp.rsplit_once(':').unwrap();
    let mut rp = RedPitaya::open(
        h,
        p.parse().unwrap(),
        RedPitayaOptions {
            calibration: Calibration {
                gain: [1.0; 3],
                offset_v: [0.0; 3],
            },
            channels: ChannelMap {
                sx: 1,
                sy: 2,
                sz: None,
            },
            ..RedPitayaOptions::default()
        },
    )
    .unwrap();

    let l = LineSweep {
        axis: 0,
        from_um: 10.0,
        to_um: 20.0,
        points: 400,
        speedupdown: 20,
        rate: 1,
        record_rate: 1,
        trigger_line: Some(1),
        table: 1,
        servo_cycle_s: DT,
    };
    Stage::move_to(&mut s, [10.0, 10.0, 5.0]).unwrap();
    LineScan::configure_line(&mut s, &l).unwrap();
    // 16 ms of the 20 ms line at ≥ 100 kHz: decimation 1024 (122 kHz), 1954 samples
    let arm = rp.arm_buffered(1600, 1e5, Trigger::ExternalRising).unwrap();
    assert_eq!(arm.n_samples, 1954);
    LineScan::start_line(&mut s, &l).unwrap();
    assert!(LineScan::wait_line(&mut s, &l, &AtomicBool::new(false)).unwrap());
    let trace = rp.read_buffered(Duration::from_secs(2)).unwrap();
    let rec = LineScan::read_line_record(&mut s, &l).unwrap();
    assert_eq!(ext.count(), 1);
    assert_eq!(rec.position_um.len(), 400);
    assert_eq!(trace.len(), 1954);
    // sample i is dated t_i after the trigger (= the generator's first servo cycle, the
    // recorder's sample 0) at the expected middle of its averaging window; its true time is
    // t_i + δ, one δ for the line with |δ| ≤ dt/2 (the decimator counts its windows from
    // `ACQ:START`). At that time the stage was where the recorder has it (linear
    // between servo cycles): find δ, then every sample agrees
    let x_at = |t: f64| {
        let u = (t / DT).max(0.0);
        let k = (u as usize).min(rec.position_um.len() - 2);
        let f = (u - k as f64).min(1.0);
        rec.position_um[k] + f * (rec.position_um[k + 1] - rec.position_um[k])
    };
    let worst = |d: f64| {
        (0..trace.len())
            .map(|i| (trace.sx[i] - linear([x_at(trace.time(i) + d), 10.0, 5.0])[0]).abs())
            .fold(0.0, f64::max)
    };
    let delta = (0..=400)
        .map(|j| trace.dt_s * (j as f64 / 400.0 - 0.5))
        .min_by(|a, b| worst(*a).total_cmp(&worst(*b)))
        .unwrap();
    assert!(
        worst(delta) < 2e-6,
        "δ = {delta} s: worst sx error {}",
        worst(delta)
    );
    for i in 0..trace.len() {
        let x = x_at(trace.time(i) + delta);
        let want = linear([x, 10.0, 5.0]);
        assert!(
            (trace.sy[i] - want[1]).abs() < 2e-6,
            "sample {i}: sy {}",
            trace.sy[i]
        );
    }
    // the stage moved during the acquisition: from 10 µm to past 17 µm
    assert!(trace.sx[0] < -0.249 && trace.sx[trace.len() - 1] > 0.1);
    // a point read afterwards is at the shared (parked) position: x = 20 µm, once the lagging
    // axis has settled there (τ = 0.5 ms; the wall time between the line's end and this read
    // varies with the machine's load, so wait for the controller to report it, ≤ 1 s)
    let t0 = std::time::Instant::now();
    while (Stage::position(&mut s).unwrap()[0] - 20.0).abs() > 1e-5 {
        assert!(
            t0.elapsed() < Duration::from_secs(1),
            "the axis never settled at 20 µm"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    let r = rp.read(100).unwrap();
    assert!((r.sx - linear([20.0, 10.0, 5.0])[0]).abs() < 1e-4, "{r}");
}
