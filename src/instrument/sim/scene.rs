//! Scenes for the simulated instrument: beads, filaments (bead model, Sec. 4.2), point-like
//! aggregates, and the list of effects to simulate.
//!
//! Coordinates: object positions are in **stage coordinates** (µm): an object at p is in the
//! focus when the stage reads p. A pixel at stage position s sees the object at displacement
//! d = s − p, so images are not mirrored and ∂Sx/∂x is positive at a bead (paper Fig. 2c).

use crate::optics::params::{check_above, check_range, OpticsError};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bead {
    pub pos: [f64; 3],
    pub d_nm: f64,
    pub n: f64,
}

/// Diameter along a filament as a function of arc length s (µm from the first point).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum DiameterProfile {
    Constant {
        d_nm: f64,
    },
    /// Linear taper from `d0_nm` at the first point to `d1_nm` at the last.
    Linear {
        d0_nm: f64,
        d1_nm: f64,
    },
    /// Parabola-of-revolution α-tip (Sec. 5): d(s) = d_nm·√(s / tip_um) for s < tip_um, then
    /// d_nm; the cross-section (mass per length) grows linearly over the tip.
    AlphaTip {
        d_nm: f64,
        tip_um: f64,
    },
}

impl DiameterProfile {
    pub fn at(&self, s: f64, length: f64) -> f64 {
        match *self {
            Self::Constant { d_nm } => d_nm,
            Self::Linear { d0_nm, d1_nm } => {
                let t = if length > 0.0 {
                    (s / length).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                d0_nm + (d1_nm - d0_nm) * t
            }
            Self::AlphaTip { d_nm, tip_um } => {
                if s >= tip_um || tip_um <= 0.0 {
                    d_nm
                } else {
                    d_nm * (s.max(0.0) / tip_um).sqrt()
                }
            }
        }
    }
    fn validate(&self) -> Result<(), OpticsError> {
        match *self {
            Self::Constant { d_nm } => check_range("d_nm", d_nm, 0.0, 5000.0).map(|_| ()),
            Self::Linear { d0_nm, d1_nm } => {
                check_range("d0_nm", d0_nm, 0.0, 5000.0)?;
                check_range("d1_nm", d1_nm, 0.0, 5000.0).map(|_| ())
            }
            Self::AlphaTip { d_nm, tip_um } => {
                check_range("d_nm", d_nm, 0.0, 5000.0)?;
                check_range("tip_um", tip_um, 0.0, 1000.0).map(|_| ())
            }
        }
    }
}

/// The simulator's default bead-model spacing of a filament, nm: 25 nm, half the paper's 50 nm
/// (Sec. 4.2). In the default vector beam 50 nm renders an α-tip 6.9e-5 of its peak off the
/// 2 nm reference, above the accuracy report's 3e-5 criterion; 25 nm is 6.7e-6, at 1.6× the
/// render time of that 64×64 image (3.0 ms against 1.85 ms, release; docs/accuracy.md#bead_spacing).
pub const FILAMENT_SPACING_NM: f64 = 25.0;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Filament {
    /// Polyline vertices (x, y) in µm, in the plane z.
    pub points: Vec<[f64; 2]>,
    pub z: f64,
    pub profile: DiameterProfile,
    pub n: f64,
    /// Bead-model spacing along the axis (paper: 50 nm; the simulator's default
    /// [`FILAMENT_SPACING_NM`]), nm.
    pub spacing_nm: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Aggregates {
    pub count: usize,
    /// Diameter range (nm); sizes uniform in volume between the two.
    pub d_nm: [f64; 2],
    pub n: f64,
    /// Region [[x0, x1], [y0, y1]] µm.
    pub region: [[f64; 2]; 2],
    pub z: f64,
    pub seed: u64,
}

/// Effect parameters. Each `Some` adds exactly one pipeline stage; `None` costs nothing.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Effects {
    pub detector_noise: Option<DetectorNoise>,
    pub laser_power_noise: Option<LaserPowerNoise>,
    pub pointing_noise: Option<PointingNoise>,
    pub drift: Option<Drift>,
    pub misalignment: Option<crate::optics::rayleigh::Misalignment>,
    pub polarization: Option<bool>,
    pub finite_size: Option<FiniteSize>,
    pub cross_terms: Option<bool>,
    pub thermal_motion: Option<ThermalMotion>,
    pub mie: Option<MieEffect>,
    pub stage_bandwidth: Option<StageBandwidth>,
    pub detector_range: Option<DetectorRange>,
}

/// A detector and digitiser of finite range (`sim::detector`): every input spans ±`range`
/// (signal units) and reads the rail beyond; the inputs see `power · Sx`, `power · Sy` and the
/// sum `sum_scale · power · (1 + Sz)`; a pixel whose sum input is below `sum_floor` is dark.
/// `power`: the fraction of the beam reaching the detector (0: laser off or beam blocked).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DetectorRange {
    pub range: f64,
    pub sum_scale: f64,
    pub sum_floor: f64,
    pub power: f64,
}

impl Default for DetectorRange {
    /// ±1 (no normalised difference reaches it), the sum at half the range, the floor at 1 %
    /// of the range, the full beam.
    fn default() -> Self {
        DetectorRange {
            range: 1.0,
            sum_scale: 0.5,
            sum_floor: 0.01,
            power: 1.0,
        }
    }
}

/// White detector noise (suppl. S8): standard deviation of one sample, in units of the beam
/// power; a read of n samples has σ/√n.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DetectorNoise {
    pub sigma_sample: f64,
}
/// Relative laser-power noise per sample (S8): multiplies the total intensity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LaserPowerNoise {
    pub sigma_rel_sample: f64,
}
/// Beam-pointing jitter and vibration (S8): random lateral displacement per sample, nm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PointingNoise {
    pub sigma_nm_sample: f64,
}
/// Stage drift (S8): constant velocity (nm/s per axis) plus a random walk (nm/√s).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Drift {
    pub velocity_nm_s: [f64; 3],
    pub random_walk_nm_sqrt_s: f64,
}
/// Finite-size decomposition of beads (S6): radial order of the sphere rule; beads smaller than
/// `min_d_nm` stay point dipoles.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FiniteSize {
    pub n_r: usize,
    pub min_d_nm: f64,
}
/// Lorenz–Mie beads (docs/physics.md §9): every scene bead of diameter ≥ `min_d_nm`
/// is rendered with the focused-beam Mie response of its sphere (angular-spectrum beam, one
/// template per distinct (d, n)) instead of a Rayleigh point dipole. Every other scatterer
/// (filaments, aggregates, smaller beads) becomes a point dipole in the same angular-spectrum
/// beam, so the scene stays one instrument. `scattered_intensity` adds the |E_s|² term of the
/// Mie spheres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MieEffect {
    pub min_d_nm: f64,
    pub scattered_intensity: bool,
}

/// A stage of finite bandwidth (hardware-timed raster lines): under the wave
/// generator the stage follows its target with a first-order lag of time constant
/// τ = 1/(2π·`hz`) (a closed-loop piezo of −3 dB bandwidth `hz`), so its measured position
/// trails the command by ≈ v·τ on a line of speed v. Point-by-point scans settle after each
/// move and do not see it. Without this effect the simulated stage follows its target exactly.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StageBandwidth {
    pub hz: f64,
}

impl StageBandwidth {
    /// The lag's time constant τ = 1/(2π·hz), s.
    pub fn tau_s(&self) -> f64 {
        1.0 / (2.0 * std::f64::consts::PI * self.hz)
    }
}

/// Thermal fluctuation of loosely bound objects (S4): rigid Gaussian jitter per object and read,
/// averaged over `samples` configurations per read (blur), σ in nm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ThermalMotion {
    pub sigma_nm: f64,
    pub samples: usize,
}

/// The paper's noise level for a 0.1 s dwell at 100 kHz (10⁴ samples): see docs/physics.md.
pub const PAPER_DETECTOR_SIGMA_SAMPLE: f64 = 2e-3;

/// Samples averaged per pixel at the paper's dwell (0.1 s at 100 kHz): with
/// [`PAPER_DETECTOR_SIGMA_SAMPLE`], the paper's per-pixel noise.
pub const PAPER_SAMPLES_PER_PIXEL: usize = 10_000;

/// All effect names, in pipeline order.
pub const EFFECT_NAMES: [&str; 12] = [
    "polarization",
    "misalignment",
    "finite_size",
    "mie",
    "thermal_motion",
    "drift",
    "stage_bandwidth",
    "pointing_noise",
    "cross_terms",
    "laser_power_noise",
    "detector_noise",
    "detector_range",
];

impl Effects {
    /// Enable one effect by name with its default parameters.
    pub fn enable(&mut self, name: &str) -> Result<(), OpticsError> {
        match name {
            "detector_noise" => {
                self.detector_noise = Some(DetectorNoise {
                    sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
                })
            }
            "laser_power_noise" => {
                self.laser_power_noise = Some(LaserPowerNoise {
                    sigma_rel_sample: 1e-3,
                })
            }
            "pointing_noise" => {
                self.pointing_noise = Some(PointingNoise {
                    sigma_nm_sample: 10.0,
                })
            }
            "drift" => {
                self.drift = Some(Drift {
                    velocity_nm_s: [0.02, 0.01, 0.005],
                    random_walk_nm_sqrt_s: 0.05,
                })
            }
            // 318 Hz: τ = 0.5 ms, the GCS emulator's default lag (a loaded closed-loop piezo)
            "stage_bandwidth" => self.stage_bandwidth = Some(StageBandwidth { hz: 318.0 }),
            "detector_range" => self.detector_range = Some(DetectorRange::default()),
            "misalignment" => self.misalignment = Some(Default::default()),
            "polarization" => self.polarization = Some(true),
            "finite_size" => {
                self.finite_size = Some(FiniteSize {
                    n_r: crate::optics::finite_size::DEFAULT_N_R,
                    min_d_nm: 0.0,
                })
            }
            "cross_terms" => self.cross_terms = Some(true),
            "thermal_motion" => {
                self.thermal_motion = Some(ThermalMotion {
                    sigma_nm: 5.0,
                    samples: 4,
                })
            }
            "mie" => {
                self.mie = Some(MieEffect {
                    min_d_nm: 0.0,
                    scattered_intensity: false,
                })
            }
            other => {
                return Err(OpticsError::Invalid(format!(
                    "unknown effect {other:?}; effects are: {}",
                    EFFECT_NAMES.join(", ")
                )))
            }
        }
        Ok(())
    }

    /// Check the effects' parameters: each names the effect, the parameter, its value and
    /// the allowed range.
    pub fn check(&self) -> Result<(), OpticsError> {
        let mut nonneg: Vec<(&str, &str, f64)> = vec![];
        if let Some(d) = self.detector_noise {
            nonneg.push(("detector_noise", "sigma_sample", d.sigma_sample));
        }
        if let Some(l) = self.laser_power_noise {
            nonneg.push(("laser_power_noise", "sigma_rel_sample", l.sigma_rel_sample));
        }
        if let Some(p) = self.pointing_noise {
            nonneg.push(("pointing_noise", "sigma_nm_sample", p.sigma_nm_sample));
        }
        if let Some(d) = self.drift {
            nonneg.push(("drift", "random_walk_nm_sqrt_s", d.random_walk_nm_sqrt_s));
            if d.velocity_nm_s.iter().any(|v| !v.is_finite()) {
                return Err(OpticsError::Invalid(format!(
                    "drift: velocity_nm_s = {:?}: must be finite",
                    d.velocity_nm_s
                )));
            }
        }
        if let Some(t) = self.thermal_motion {
            nonneg.push(("thermal_motion", "sigma_nm", t.sigma_nm));
        }
        for (fx, k, v) in nonneg {
            if !(v.is_finite() && v >= 0.0) {
                return Err(OpticsError::Invalid(format!(
                    "{fx}: {k} = {v}: must be finite and ≥ 0"
                )));
            }
        }
        if let Some(d) = self.detector_range {
            for (k, v, lo) in [
                ("range", d.range, "> 0"),
                ("sum_scale", d.sum_scale, "> 0"),
                ("sum_floor", d.sum_floor, "≥ 0"),
                ("power", d.power, "≥ 0"),
            ] {
                let ok = v.is_finite() && if lo == "> 0" { v > 0.0 } else { v >= 0.0 };
                if !ok {
                    return Err(OpticsError::Invalid(format!(
                        "detector_range: {k} = {v}: must be finite and {lo}"
                    )));
                }
            }
        }
        if let Some(b) = self.stage_bandwidth {
            if !(b.hz.is_finite() && b.hz > 0.0) {
                return Err(OpticsError::Invalid(format!(
                    "stage_bandwidth: hz = {}: must be finite and > 0",
                    b.hz
                )));
            }
        }
        Ok(())
    }

    /// Names of the enabled effects, in pipeline order.
    pub fn names(&self) -> Vec<&'static str> {
        let on = [
            ("polarization", self.polarization == Some(true)),
            ("misalignment", self.misalignment.is_some()),
            ("finite_size", self.finite_size.is_some()),
            ("mie", self.mie.is_some()),
            ("thermal_motion", self.thermal_motion.is_some()),
            ("drift", self.drift.is_some()),
            ("stage_bandwidth", self.stage_bandwidth.is_some()),
            ("pointing_noise", self.pointing_noise.is_some()),
            ("cross_terms", self.cross_terms == Some(true)),
            ("laser_power_noise", self.laser_power_noise.is_some()),
            ("detector_noise", self.detector_noise.is_some()),
            ("detector_range", self.detector_range.is_some()),
        ];
        on.iter().filter(|(_, b)| *b).map(|(n, _)| *n).collect()
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    pub beads: Vec<Bead>,
    pub filaments: Vec<Filament>,
    pub aggregates: Vec<Aggregates>,
    pub effects: Effects,
    /// Seed of every random effect (noise, drift, thermal motion).
    pub seed: u64,
}

/// One point scatterer of the expanded scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scatterer {
    pub pos: [f64; 3],
    /// Polarisability α = r³·CM (times the bead-model volume factor), µm³.
    pub alpha: f64,
    /// Which scene object it belongs to (rigid thermal motion moves objects, not scatterers).
    pub object: usize,
    /// Diameter for finite-size decomposition (beads only), nm.
    pub d_nm: Option<f64>,
}

impl Scene {
    pub fn add_bead(&mut self, b: Bead) -> Result<(), OpticsError> {
        for (name, v) in [("x", b.pos[0]), ("y", b.pos[1]), ("z", b.pos[2])] {
            check_range(name, v, -1e4, 1e4)?;
        }
        check_range("d_nm", b.d_nm, 0.0, 20000.0)?;
        if b.d_nm <= 0.0 {
            return Err(OpticsError::Invalid(format!(
                "d_nm = {} nm: a bead needs a positive diameter (0 < d_nm ≤ 20000 nm)",
                b.d_nm
            )));
        }
        check_range("n", b.n, 1.0, 5.0)?;
        self.beads.push(b);
        Ok(())
    }

    pub fn add_filament(&mut self, f: Filament) -> Result<(), OpticsError> {
        if f.points.is_empty() {
            return Err(OpticsError::Invalid(
                "add_filament: points is empty; give at least one [x, y] vertex".into(),
            ));
        }
        for p in &f.points {
            check_range("points[..][0] (x)", p[0], -1e4, 1e4)?;
            check_range("points[..][1] (y)", p[1], -1e4, 1e4)?;
        }
        check_range("z", f.z, -1e4, 1e4)?;
        check_range("n", f.n, 1.0, 5.0)?;
        check_range("spacing_nm", f.spacing_nm, 1.0, 1000.0)?;
        f.profile.validate()?;
        self.filaments.push(f);
        Ok(())
    }

    pub fn add_aggregates(&mut self, a: Aggregates) -> Result<(), OpticsError> {
        check_range("count", a.count as f64, 0.0, 100000.0)?;
        check_range("d_nm[0]", a.d_nm[0], 0.0, 5000.0)?;
        check_range("d_nm[1]", a.d_nm[1], a.d_nm[0], 5000.0)?;
        check_range("n", a.n, 1.0, 5.0)?;
        for r in a.region {
            check_above("region width (µm)", r[1] - r[0], -1e-300)?;
        }
        self.aggregates.push(a);
        Ok(())
    }

    /// Rotate every object by `angle_deg` (counter-clockwise) about `centre` in the xy plane —
    /// what the operator does to the sample in the 19-angle rotation series.
    pub fn rotate(&mut self, angle_deg: f64, centre: [f64; 2]) {
        let (s, c) = angle_deg.to_radians().sin_cos();
        let rot = |p: [f64; 2]| {
            let (dx, dy) = (p[0] - centre[0], p[1] - centre[1]);
            [centre[0] + c * dx - s * dy, centre[1] + s * dx + c * dy]
        };
        for b in &mut self.beads {
            let r = rot([b.pos[0], b.pos[1]]);
            b.pos[0] = r[0];
            b.pos[1] = r[1];
        }
        for f in &mut self.filaments {
            for p in &mut f.points {
                *p = rot(*p);
            }
        }
        // aggregates are generated from their seeds: make them explicit beads, then rotate
        let expanded = self.aggregate_beads();
        self.aggregates.clear();
        for mut b in expanded {
            let r = rot([b.pos[0], b.pos[1]]);
            b.pos[0] = r[0];
            b.pos[1] = r[1];
            self.beads.push(b);
        }
    }

    /// Aggregates as explicit beads (deterministic from their seeds).
    pub fn aggregate_beads(&self) -> Vec<Bead> {
        let mut out = vec![];
        for a in &self.aggregates {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
            let (v0, v1) = (a.d_nm[0].powi(3), a.d_nm[1].powi(3));
            for _ in 0..a.count {
                let x = a.region[0][0] + (a.region[0][1] - a.region[0][0]) * rng.random::<f64>();
                let y = a.region[1][0] + (a.region[1][1] - a.region[1][0]) * rng.random::<f64>();
                let d = (v0 + (v1 - v0) * rng.random::<f64>()).cbrt();
                out.push(Bead {
                    pos: [x, y, a.z],
                    d_nm: d,
                    n: a.n,
                });
            }
        }
        out
    }

    /// Expand every object into point scatterers (bead model for filaments, Sec. 4.2: spheres of
    /// the local radius r every h along the axis, each with volume factor 3h/4r, i.e.
    /// α = (3/4)·h·r²·CM).
    pub fn scatterers(&self, n_medium: f64) -> Vec<Scatterer> {
        use crate::optics::rayleigh::{alpha_um3, clausius_mossotti};
        let mut out = vec![];
        let mut obj = 0;
        for b in self.beads.iter().chain(self.aggregate_beads().iter()) {
            out.push(Scatterer {
                pos: b.pos,
                alpha: alpha_um3(b.d_nm, b.n, n_medium),
                object: obj,
                d_nm: Some(b.d_nm),
            });
            obj += 1;
        }
        for f in &self.filaments {
            let cm = clausius_mossotti(f.n, n_medium);
            let h = f.spacing_nm * 1e-3;
            let seg_len = crate::data::segment_lengths(&f.points);
            let length: f64 = seg_len.iter().sum();
            // one bead-model section of length `dl` centred at arc length `s`, at `p`
            let section = move |p: [f64; 2], s: f64, dl: f64| {
                let r = 0.5e-3 * f.profile.at(s, length);
                Scatterer {
                    pos: [p[0], p[1], f.z],
                    alpha: 0.75 * dl * r * r * cm,
                    object: obj,
                    d_nm: None,
                }
            };
            let nb = (length / h).round() as usize;
            if nb == 0 {
                // a zero-length filament (or shorter than one spacing) is a single bead-model
                // section of length `length` at its start: nothing if the length is zero.
                if length > 0.0 {
                    out.push(section(f.points[0], 0.0, length));
                }
                obj += 1;
                continue;
            }
            let hh = length / nb as f64; // spacing adjusted to fit the length exactly
            for i in 0..nb {
                let s = (i as f64 + 0.5) * hh;
                // locate s on the polyline
                let (mut acc, mut p) = (0.0, f.points[0]);
                for (k, &l) in seg_len.iter().enumerate() {
                    if s <= acc + l || k == seg_len.len() - 1 {
                        let t = if l > 0.0 {
                            ((s - acc) / l).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        let (a, b) = (f.points[k], f.points[k + 1]);
                        p = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                        break;
                    }
                    acc += l;
                }
                out.push(section(p, s, hh));
            }
            obj += 1;
        }
        out
    }
}
