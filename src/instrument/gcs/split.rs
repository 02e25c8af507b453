//! A stage split across PI GCS controllers: XY on an E-727 and Z on an E-709 on a second port,
//! or one single-axis controller per axis. Each controller is a [`GcsStage`] driving its own
//! axes; this stage fans every call out to them and puts x, y, z back together.
//!
//! A move sends each controller's `MOV` (only the axes whose target changes), then waits for
//! each to report on target. `stop` sends `STP` to every controller, also when one of them
//! fails to answer: a fault on one puts the state of all in doubt.

use super::{GcsOptions, GcsStage, PerAxis};
use crate::instrument::device::all_then_first_error;
use crate::instrument::{DeviceError, Pos, Stage};
use std::sync::atomic::AtomicBool;

const XYZ: [&str; 3] = ["x", "y", "z"];

/// Several GCS controllers making one x, y, z stage.
pub struct GcsSplitStage {
    parts: Vec<GcsStage>,
}

impl GcsSplitStage {
    /// Open every controller (port, settings naming the axes it drives) without switching
    /// anything on (see [`GcsStage::open_checked`]); [`Stage::enable`] switches their servos
    /// on. Each of x, y, z must be driven by exactly one controller. If one fails to open,
    /// the ones already opened are closed again, untouched.
    pub fn open_checked(
        controllers: &[(String, GcsOptions)],
        baud: u32,
    ) -> Result<Self, DeviceError> {
        let mut owner: [Option<&str>; 3] = [None; 3];
        for (port, o) in controllers {
            for (i, a) in o.axes.iter().enumerate() {
                if a.is_some() {
                    if let Some(other) = owner[i] {
                        return Err(DeviceError::Other {
                            device: format!("GCS stage on {port}"),
                            detail: format!("axis {} is driven by {other} too", XYZ[i]),
                        });
                    }
                    owner[i] = Some(port);
                }
            }
        }
        if let Some(i) = owner.iter().position(Option::is_none) {
            return Err(DeviceError::Other {
                device: "GCS stage".into(),
                detail: format!("no controller drives axis {}", XYZ[i]),
            });
        }
        let mut parts = Vec::with_capacity(controllers.len());
        for (port, o) in controllers {
            parts.push(GcsStage::open_checked(port, baud, o.clone())?);
        }
        Ok(Self { parts })
    }

    /// The controllers, in x, y, z order of their first axis.
    pub fn controllers(&self) -> &[GcsStage] {
        &self.parts
    }

    fn merge(
        &mut self,
        f: impl Fn(&mut GcsStage) -> Result<PerAxis<f64>, DeviceError>,
    ) -> Result<Pos, DeviceError> {
        let mut out = [f64::NAN; 3];
        for p in &mut self.parts {
            for (i, v) in f(p)?.iter().enumerate() {
                if let Some(v) = v {
                    out[i] = *v;
                }
            }
        }
        Ok(out)
    }

    fn each(
        &mut self,
        f: impl Fn(&mut GcsStage) -> Result<(), DeviceError>,
    ) -> Result<(), DeviceError> {
        for p in &mut self.parts {
            f(p)?;
        }
        Ok(())
    }
}

impl Stage for GcsSplitStage {
    /// `PI E-727 on /dev/ttyUSB0 (x, y) + PI E-709 on /dev/ttyUSB2 (z)`.
    fn name(&self) -> String {
        self.parts
            .iter()
            .map(|p| {
                let axes: Vec<&str> = p.driven().iter().map(|&i| XYZ[i]).collect();
                format!("{} ({})", p.name(), axes.join(", "))
            })
            .collect::<Vec<_>>()
            .join(" + ")
    }

    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.merge(|p| p.read_axes("POS?"))
    }

    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.merge(|p| p.commanded_partial())
    }

    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.move_to_or_abort(target, &AtomicBool::new(false))
            .map(|_| ())
    }

    /// Every controller's `MOV` first (the axes move together), then each one's on-target wait.
    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        let mut sent = Vec::new();
        for (k, p) in self.parts.iter_mut().enumerate() {
            if let Some(cmd) = p.move_no_wait(target)? {
                sent.push((k, cmd));
            }
        }
        for (k, cmd) in sent {
            if !self.parts[k].wait_on_target_or_abort(&cmd, Some(abort))? {
                return Ok(false);
            }
        }
        Ok(true)
    }

    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        let lo = self.merge(|p| p.read_axes("TMN?"))?;
        let hi = self.merge(|p| p.read_axes("TMX?"))?;
        Ok([(lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])])
    }

    /// `STP` to every controller, even when one fails; the first failure is reported.
    fn stop(&mut self) -> Result<(), DeviceError> {
        all_then_first_error(&mut self.parts, |p| p.send_stop())
    }

    fn enable(&mut self) -> Result<(), DeviceError> {
        self.each(GcsStage::enable)
    }

    fn set_velocity(&mut self, um_s: f64) -> Result<(), DeviceError> {
        self.each(|p| p.send_velocity(um_s))
    }

    fn velocity(&mut self) -> Result<Option<Pos>, DeviceError> {
        self.merge(|p| p.read_axes("VEL?")).map(Some)
    }

    /// The slowest controller's mean move time.
    fn move_time_s(&self) -> f64 {
        self.parts
            .iter()
            .map(GcsStage::mean_move_s)
            .fold(0.0, f64::max)
    }

    /// Every controller's costs, summed per command word.
    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        crate::instrument::link::summed_costs(self.parts.iter_mut().map(|p| p.take_link_costs()))
    }

    crate::instrument::stage_capabilities!(RawQuery);
}

/// Raw GCS queries at the prompt (`gcs_query`), to every controller.
impl crate::instrument::RawQuery for GcsSplitStage {
    /// The query to every controller; each reply line is prefixed with the controller's name.
    fn raw_query(&mut self, query: &str) -> Result<Vec<String>, DeviceError> {
        let mut out = Vec::new();
        for p in &mut self.parts {
            let name = p.name();
            out.extend(
                p.query_only(query)?
                    .into_iter()
                    .map(|l| format!("{name}: {l}")),
            );
        }
        Ok(out)
    }
}
