//! The state of the GCS stage emulator's wave generator, data recorder and trigger outputs
//! (tables, generators, record tables, trigger lines, the servo clock), with the settings it is
//! built from. The commands that change it (`WAV`, `WGO`, `DRC`, `CTO`, …) are `GcsDevice`'s,
//! in `wave.rs`; `stage.rs` holds one [`Wave`]. A leaf of `stage/`: it names neither.

use crate::instrument::emulation::{ExtTrigger, StagePath};
use std::collections::BTreeMap;
use std::time::Instant;

/// Wave generator, data recorder and trigger-output settings of the stage emulator.
#[derive(Debug, Clone, PartialEq)]
pub struct WaveConfig {
    /// Servo cycle of the controller, s (the clock of the generator and the recorder).
    pub servo_cycle_s: f64,
    /// Time constant τ of the axis' first-order lag under the wave generator, s (0: none).
    pub lag_s: f64,
    /// Number of wave tables (ids 1…n).
    pub tables: usize,
    /// Most points a wave table holds.
    pub table_points: usize,
    /// Number of data recorder tables (ids 1…n).
    pub record_tables: usize,
    /// Most points a record table holds.
    pub record_points: usize,
    /// What the digital outputs OUT1…OUT3 are wired to (a digitiser's external trigger).
    pub trigger_out: [Option<ExtTrigger>; 3],
    /// Where the path of a running wave is published for a digitiser that samples the stage
    /// during a whole acquisition (see [`StagePath`]).
    pub path: Option<StagePath>,
}

impl Default for WaveConfig {
    /// 50 µs servo cycle, τ = 0.5 ms, 8 wave tables of 65 536 points, 8 record tables of
    /// 65 536 points, outputs not wired.
    fn default() -> Self {
        Self {
            servo_cycle_s: 50e-6,
            lag_s: 0.5e-3,
            tables: 8,
            table_points: 65_536,
            record_tables: 8,
            record_points: 65_536,
            trigger_out: [None, None, None],
            path: None,
        }
    }
}

#[derive(Debug, Clone, Default)]
pub(super) struct Gen {
    pub(super) table: usize,
    pub(super) cycles: u32,
    pub(super) rate: u32,
    pub(super) interp: u32,
    pub(super) mode: u32,
    pub(super) running: bool,
    pub(super) start: u64,
    /// Point index output in the last cycle.
    pub(super) point: usize,
}

#[derive(Debug, Clone)]
pub(super) struct Rec {
    pub(super) axis: usize,
    pub(super) option: u32,
    pub(super) data: Vec<f64>,
}

#[derive(Debug, Clone, Default)]
pub(super) struct TrigLine {
    pub(super) axis: usize,
    pub(super) mode: Option<u32>,
    pub(super) step: f64,
    pub(super) min: f64,
    pub(super) max: f64,
    pub(super) polarity: u32,
    pub(super) start: f64,
    pub(super) stop: f64,
    /// Active level in the last cycle.
    pub(super) level: bool,
    /// Position distance: the position of the next pulse.
    pub(super) next: Option<f64>,
    /// Last position seen (for threshold crossings).
    pub(super) last_x: Option<f64>,
    /// Generator trigger: level per wave point (1-based).
    pub(super) tws: BTreeMap<usize, bool>,
}

/// The state of the wave generator, recorder and trigger outputs.
pub(super) struct Wave {
    pub(super) cfg: WaveConfig,
    pub(super) tables: Vec<Vec<f64>>,
    pub(super) gens: [Gen; 3],
    pub(super) rec: Vec<Rec>,
    pub(super) rtr: u32,
    pub(super) drt: u32,
    /// Recording: the cycle of the first sample.
    pub(super) rec_start: Option<u64>,
    pub(super) lines: [TrigLine; 3],
    pub(super) clock0: Instant,
    /// Last servo cycle computed.
    pub(super) cycle: u64,
    pub(super) alpha: f64,
}

impl Wave {
    pub(super) fn new(cfg: WaveConfig, now: Instant) -> Self {
        let dt = cfg.servo_cycle_s.max(1e-7);
        let alpha = if cfg.lag_s > 0.0 {
            1.0 - (-dt / cfg.lag_s).exp()
        } else {
            1.0
        };
        let gen = Gen {
            rate: 1,
            cycles: 1,
            ..Gen::default()
        };
        let line = TrigLine {
            polarity: 1,
            ..TrigLine::default()
        };
        Self {
            tables: vec![Vec::new(); cfg.tables],
            rec: (0..cfg.record_tables)
                .map(|i| Rec {
                    axis: i % 3,
                    option: 0,
                    data: Vec::new(),
                })
                .collect(),
            gens: [gen.clone(), gen.clone(), gen],
            rtr: 1,
            drt: 0,
            rec_start: None,
            lines: [
                TrigLine {
                    axis: 0,
                    ..line.clone()
                },
                TrigLine {
                    axis: 1,
                    ..line.clone()
                },
                TrigLine { axis: 2, ..line },
            ],
            clock0: now,
            cycle: 0,
            alpha,
            cfg,
        }
    }

    pub(super) fn dt(&self) -> f64 {
        self.cfg.servo_cycle_s.max(1e-7)
    }

    /// The servo cycle at `now`.
    pub(super) fn cycle_at(&self, now: Instant) -> u64 {
        (now.duration_since(self.clock0).as_secs_f64() / self.dt()) as u64
    }

    /// The instant of servo cycle `k`.
    pub(super) fn instant_of(&self, k: u64) -> Instant {
        self.clock0 + std::time::Duration::from_secs_f64(k as f64 * self.dt())
    }

    /// True if generator `i` is running.
    pub(super) fn running(&self, i: usize) -> bool {
        self.gens[i].running
    }

    /// Stop every generator (`STP`, `HLT`, `#24`); they hold their last output.
    pub(super) fn stop_all(&mut self) {
        if self.gens.iter().any(|g| g.running) {
            self.truncate_path();
        }
        for g in &mut self.gens {
            g.running = false;
        }
    }

    /// The published path ends at the current servo cycle.
    pub(super) fn truncate_path(&mut self) {
        if let Some(p) = &self.cfg.path {
            if let Some(d) = p.get() {
                let k0 = self.cycle_of(d.start);
                p.truncate(self.cycle.saturating_sub(k0) as usize);
            }
        }
    }

    /// The servo cycle whose instant is `t` (the inverse of [`instant_of`](Self::instant_of)).
    pub(super) fn cycle_of(&self, t: Instant) -> u64 {
        (t.saturating_duration_since(self.clock0).as_secs_f64() / self.dt()).round() as u64
    }

    /// A `MOV` took the axes over: no wave path any more.
    pub(super) fn clear_path(&mut self) {
        if let Some(p) = &self.cfg.path {
            p.clear();
        }
    }

    /// A position-changing command (`MOV`) was accepted: `DRT 1` starts recording.
    pub(super) fn position_command(&mut self) {
        if self.drt == 1 {
            self.trigger_recording();
        }
    }

    pub(super) fn trigger_recording(&mut self) {
        for r in &mut self.rec {
            r.data.clear();
        }
        self.rec_start = Some(self.cycle + 1);
    }

    /// True while anything needs the servo clock stepped.
    pub(super) fn busy(&self, dev_lagging: bool) -> bool {
        dev_lagging
            || self.gens.iter().any(|g| g.running)
            || self.rec_start.is_some()
            || self
                .lines
                .iter()
                .enumerate()
                .any(|(i, l)| l.mode.is_some() && self.cfg.trigger_out[i].is_some())
    }
}
