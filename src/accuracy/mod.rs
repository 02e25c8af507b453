//! What accuracy costs in time (issue 7): for each approximation knob, sweep its values and
//! measure, in one run on this machine, the error against a high-accuracy reference computed in
//! the same run and the time spent (median of repeats). `bfpscope accuracy` writes the tables and
//! Pareto plots to docs/accuracy.md.

pub mod analysis_knobs;
pub mod instrument;
pub mod mie_knobs;
pub mod report;

use crate::instrument::sim::scene::{DiameterProfile, Filament, Scene};
use crate::instrument::sim::{render_xy, Renderer};
use crate::optics::finite_size::max_sensitivity_unit;
use crate::optics::grid::Interp;
use crate::optics::params::Optics;
use crate::optics::rayleigh::{Detection, DetectorModel};
use crate::optics::template::{ModelTemplate, TemplateSpec};
use serde::Serialize;
use std::sync::Arc;
use std::time::Instant;

/// One setting of a knob: its error and its cost.
#[derive(Debug, Clone, Serialize)]
pub struct Point {
    pub setting: String,
    /// Numeric value of the knob (for plots).
    pub value: f64,
    pub error: f64,
    pub seconds: f64,
    pub is_default: bool,
}

/// The sweep of one knob.
#[derive(Debug, Clone, Serialize)]
pub struct Knob {
    /// Short id (file names).
    pub id: String,
    pub title: String,
    pub metric: String,
    pub timed: String,
    pub reference: String,
    pub points: Vec<Point>,
}

impl Knob {
    pub fn default_point(&self) -> Option<&Point> {
        self.points.iter().find(|p| p.is_default)
    }
}

/// Median wall time of `reps` runs of `f`, seconds.
pub fn time_median<T>(reps: usize, mut f: impl FnMut() -> T) -> f64 {
    let mut t: Vec<f64> = (0..reps.max(1))
        .map(|_| {
            let s = Instant::now();
            std::hint::black_box(f());
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[t.len() / 2]
}

fn test_points() -> Vec<(f64, f64, f64)> {
    vec![
        (0.1, 0.0, 0.0),
        (0.3, 0.2, 0.0),
        (0.8, -0.5, 0.3),
        (1.2, 0.4, -0.5),
        (0.0, 0.0, 0.7),
        (2.0, 1.0, 1.5),
        (-0.45, 0.6, 0.1),
    ]
}

/// Cone quadrature order: worst error of (Sx, Sy, Sz) over test points relative to the peak Sx,
/// against a (128, 64) rule; time of one response evaluation.
pub fn knob_quadrature(quick: bool) -> Knob {
    quadrature_sweep(
        quick,
        DetectorModel::default(),
        "quadrature",
        "Quadrature order over the detection cone",
    )
}

/// The same sweep with the `misalignment` effect: the QPD's sign boundaries no longer fall on
/// rule boundaries, so convergence is algebraic.
pub fn knob_quadrature_misaligned(quick: bool) -> Knob {
    let m = DetectorModel {
        polarization: false,
        misalignment: Some(Default::default()),
    };
    quadrature_sweep(
        quick,
        m,
        "quadrature_misaligned",
        "Quadrature order, misaligned QPD",
    )
}

fn quadrature_sweep(quick: bool, model: DetectorModel, id: &str, title: &str) -> Knob {
    let base = Optics::default();
    let r = Detection::new(
        &Optics {
            n_theta: 128,
            n_phi: 64,
            ..base.clone()
        },
        &model,
    )
    .unwrap();
    let peak = r.response_unit(0.25, 0.0, 0.0).0[0].abs();
    let orders: &[usize] = if quick {
        &[8, 16, 24, 48]
    } else {
        &[6, 8, 12, 16, 24, 32, 48, 64]
    };
    let pts = test_points();
    let points = orders
        .iter()
        .map(|&nt| {
            let o = Optics {
                n_theta: nt,
                n_phi: nt / 2,
                ..base.clone()
            };
            let d = Detection::new(&o, &model).unwrap();
            let mut worst: f64 = 0.0;
            for &(x, y, z) in &pts {
                let (a, b) = (d.response_unit(x, y, z).0, r.response_unit(x, y, z).0);
                for c in 0..3 {
                    worst = worst.max((a[c] - b[c]).abs() / peak);
                }
            }
            let secs = time_median(if quick { 5 } else { 21 }, || {
                d.response_unit(0.31, -0.12, 0.05)
            });
            Point {
                setting: format!("n_theta = {nt}, n_phi = {}", nt / 2),
                value: (4 * nt * (nt / 2)) as f64,
                error: worst.max(1e-16),
                seconds: secs,
                is_default: nt == base.n_theta && nt / 2 == base.n_phi,
            }
        })
        .collect();
    Knob {
        id: id.into(),
        title: title.into(),
        metric: "worst |ΔS| over 7 points out to (2, 1, 1.5) µm, relative to peak Sx".into(),
        timed: "one point response (Sx, Sy, Sz and x/y derivatives)".into(),
        reference: "Gauss–Legendre (128, 64)".into(),
        points,
    }
}

/// Template grid spacing and interpolation: RMS error of a 64×64 image of a 110 nm bead at an
/// off-plane height (z = 0.137 µm, so z is interpolated too) against direct evaluation, relative
/// to the peak; time to build the template planes and render the image.
pub fn knob_template(quick: bool) -> Knob {
    let o = Optics::default();
    let det = Arc::new(Detection::new(&o, &DetectorModel::default()).unwrap());
    let z = 0.137;
    let n = if quick { 32 } else { 64 };
    let xs: Vec<f64> = (0..n)
        .map(|i| -1.0 + 2.0 * i as f64 / (n - 1) as f64)
        .collect();
    let mut truth = vec![];
    for &y in &xs {
        for &x in &xs {
            truth.push(det.response_unit(x, y, z).0[0]);
        }
    }
    let peak = truth.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let hs: &[f64] = if quick {
        &[0.08, 0.04, 0.02]
    } else {
        &[0.1, 0.08, 0.04, 0.02, 0.01]
    };
    let mut points = vec![];
    for interp in [Interp::Linear, Interp::Cubic] {
        for &h in hs {
            let spec = TemplateSpec {
                h,
                hz: 0.05,
                interp,
            };
            let mut err = 0.0;
            let secs = time_median(if quick { 1 } else { 3 }, || {
                let t = ModelTemplate::new(det.clone(), spec).unwrap();
                let mut s2 = 0.0;
                let mut k = 0;
                for &y in &xs {
                    for &x in &xs {
                        s2 += (t.eval(x, y, z)[0] - truth[k]).powi(2);
                        k += 1;
                    }
                }
                err = (s2 / k as f64).sqrt() / peak;
            });
            points.push(Point {
                setting: format!("{interp:?}, h = {} nm", h * 1e3),
                value: h * 1e3,
                error: err.max(1e-16),
                seconds: secs,
                is_default: spec == TemplateSpec::default(),
            });
        }
    }
    Knob {
        id: "template".into(),
        title: "Template grid spacing h and interpolation (hz = 50 nm)".into(),
        metric: format!("RMS error of a {n}×{n} Sx image at z = 0.137 µm, relative to its peak"),
        timed: "build the template planes + evaluate the image".into(),
        reference: "direct cone quadrature at every pixel".into(),
        points,
    }
}

/// Bead-model spacing: RMS error of a 64×64 Sx image of a collagen α-tip (100 nm, 3 µm tip,
/// along y, Sec. 5) against 2 nm spacing, relative to the image peak; time to render the image.
/// (For a uniform straight filament the bead sum converges like e^{−π²w0²/h²}; the tip's changing
/// diameter is what a coarse spacing misses.)
pub fn knob_bead_spacing(quick: bool) -> Knob {
    let o = Optics::default();
    let n = if quick { 32 } else { 64 };
    let xs: Vec<f64> = (0..n)
        .map(|i| -1.0 + 2.0 * i as f64 / (n - 1) as f64)
        .collect();
    let ys: Vec<f64> = (0..n)
        .map(|i| -0.5 + 3.0 * i as f64 / (n - 1) as f64)
        .collect();
    let renderer = |spacing_nm: f64| -> Renderer {
        let mut s = Scene::default();
        s.add_filament(Filament {
            points: vec![[0.0, 0.0], [0.0, 8.0]],
            z: 0.0,
            profile: DiameterProfile::AlphaTip {
                d_nm: 100.0,
                tip_um: 3.0,
            },
            n: 1.414,
            spacing_nm,
        })
        .unwrap();
        Renderer::checked(&o, &s, TemplateSpec::default()).unwrap()
    };
    let reference = render_xy(&renderer(2.0), &xs, &ys, 0.0, 1).sx.data;
    let peak = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let spacings: &[f64] = if quick {
        &[200.0, 100.0, 50.0, 25.0]
    } else {
        &[400.0, 200.0, 100.0, 50.0, 25.0, 10.0]
    };
    let points = spacings
        .iter()
        .map(|&sp| {
            let r = renderer(sp);
            let img = render_xy(&r, &xs, &ys, 0.0, 1).sx.data;
            let rms = ((&img - &reference).mapv(|v| v * v).sum() / img.len() as f64).sqrt() / peak;
            let secs = time_median(if quick { 3 } else { 7 }, || {
                render_xy(&r, &xs, &ys, 0.0, 1)
            });
            Point {
                setting: format!("{sp} nm"),
                value: sp,
                error: rms.max(1e-16),
                seconds: secs,
                is_default: sp == crate::instrument::sim::scene::FILAMENT_SPACING_NM,
            }
        })
        .collect();
    Knob {
        id: "bead_spacing".into(),
        title: "Bead-model spacing along a filament (α-tip)".into(),
        metric: format!(
            "RMS error of a {n}×{n} Sx image of a 100 nm fibril's 3 µm α-tip, relative to its peak"
        ),
        timed: "render the image (template ready)".into(),
        reference: "2 nm spacing".into(),
        points,
    }
}

/// Finite-size sphere rule order: relative error of the max sensitivity of a 500 nm bead
/// against n_r = 14; time of one max-sensitivity evaluation at the focus.
pub fn knob_finite_size(quick: bool) -> Knob {
    let det = Detection::new(&Optics::default(), &DetectorModel::default()).unwrap();
    let d = 500.0;
    let at0 = |n_r: usize| bfpscope_fs_sens(&det, d, n_r);
    let reference = at0(14);
    let orders: &[usize] = if quick {
        &[1, 2, 4, 6]
    } else {
        &[1, 2, 3, 4, 6, 9]
    };
    let points = orders
        .iter()
        .map(|&n| {
            let v = at0(n);
            let secs = time_median(if quick { 3 } else { 7 }, || at0(n));
            Point {
                setting: format!("n_r = {n} ({} dipoles)", 2 * n * n * n),
                value: (2 * n * n * n) as f64,
                error: ((v - reference) / reference).abs().max(1e-16),
                seconds: secs,
                is_default: n == crate::optics::finite_size::DEFAULT_N_R,
            }
        })
        .collect();
    let _ = max_sensitivity_unit; // the full focus search uses the same rule
    Knob {
        id: "finite_size".into(),
        title: "Finite-size sphere rule (suppl. S6), 500 nm bead".into(),
        metric: "relative error of ∂Sx/∂x at the bead centre, z = 0".into(),
        timed: "one sensitivity evaluation of the decomposed sphere".into(),
        reference: "n_r = 14 (5488 dipoles)".into(),
        points,
    }
}

fn bfpscope_fs_sens(det: &Detection, d_nm: f64, n_r: usize) -> f64 {
    crate::optics::finite_size::response_unit_finite(det, d_nm, n_r, 0.0, 0.0, 0.0).1[0]
}

/// What the paper's approximation costs (issue 19 item 2): the paraxial scalar Gaussian of
/// suppl. S3 against the default instrument, the aplanatic vector focus of a uniformly filled
/// NA 1.2 objective (validated against an independent Richards–Wolf model, docs/physics.md §10).
/// Error: RMS of an n×n Sx image of a 110 nm polystyrene bead relative to the vector beam's
/// peak; time: build the renderer (templates from scratch) and render the image.
pub fn knob_beam(quick: bool) -> Knob {
    use crate::optics::params::Beam;
    let n = if quick { 32 } else { 64 };
    let xs: Vec<f64> = (0..n)
        .map(|i| -1.2 + 2.4 * i as f64 / (n - 1) as f64)
        .collect();
    let mut s = Scene::default();
    s.add_bead(crate::instrument::sim::scene::Bead {
        pos: [0.05, -0.03, 0.0],
        d_nm: crate::optics::params::REF_BEAD_D_NM,
        n: crate::optics::params::REF_BEAD_N,
    })
    .expect("valid bead");
    let image = |beam: Beam| {
        let o = Optics {
            beam,
            ..Optics::default()
        };
        let r = Renderer::checked(&o, &s, TemplateSpec::default()).expect("default optics");
        render_xy(&r, &xs, &xs, 0.0, 1).sx.data
    };
    let reference = image(Beam::Vector);
    let peak = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let points = [Beam::Paraxial, Beam::Vector]
        .into_iter()
        .enumerate()
        .map(|(i, beam)| {
            let img = image(beam);
            let rms = ((&img - &reference).mapv(|v| v * v).sum() / img.len() as f64).sqrt() / peak;
            Point {
                setting: beam.name().into(),
                value: i as f64,
                error: rms.max(1e-16),
                seconds: time_median(if quick { 1 } else { 3 }, || image(beam)),
                is_default: beam == Optics::default().beam,
            }
        })
        .collect();
    Knob {
        id: "beam".into(),
        title: "Beam model: what the paper's paraxial approximation costs".into(),
        metric: format!(
            "RMS error of a {n}×{n} Sx image of a 110 nm polystyrene bead relative to the vector beam's peak"
        ),
        timed: "build the renderer (templates from scratch) and render the image".into(),
        reference: "the aplanatic vector beam (docs/physics.md §10)".into(),
        points,
    }
}

/// Every physics knob, in report order.
pub fn physics_knobs(quick: bool) -> Vec<Knob> {
    vec![
        knob_beam(quick),
        knob_quadrature(quick),
        knob_quadrature_misaligned(quick),
        knob_template(quick),
        knob_bead_spacing(quick),
        knob_finite_size(quick),
    ]
}

/// The knee of a sweep: the cheapest point whose error is within 3× of the best error or below
/// `good_enough` (the report uses 3e-5 of the peak: even averaged over a 64×64 fit region the paper's per-pixel
/// noise, 0.84% of the peak, is 1.3e-4 — four times larger).
pub fn knee(k: &Knob, good_enough: f64) -> Option<&Point> {
    let best = k
        .points
        .iter()
        .map(|p| p.error)
        .fold(f64::INFINITY, f64::min);
    k.points
        .iter()
        .filter(|p| p.error <= (3.0 * best).max(good_enough))
        .min_by(|a, b| a.seconds.total_cmp(&b.seconds))
}

/// Markdown table of one knob.
pub fn markdown_table(k: &Knob) -> String {
    let mut s = format!(
        "### {}\n\nError: {} (reference: {}). Time: {} (median of repeats).\n\n| setting | error | time | |\n|---|---|---|---|\n",
        k.title, k.metric, k.reference, k.timed
    );
    for p in &k.points {
        s += &format!(
            "| {} | {:.2e} | {} | {} |\n",
            p.setting,
            p.error,
            fmt_secs(p.seconds),
            if p.is_default { "**default**" } else { "" }
        );
    }
    s
}

pub fn fmt_secs(s: f64) -> String {
    if s < 1e-6 {
        format!("{:.0} ns", s * 1e9)
    } else if s < 1e-3 {
        format!("{:.1} µs", s * 1e6)
    } else if s < 1.0 {
        format!("{:.1} ms", s * 1e3)
    } else {
        format!("{s:.2} s")
    }
}

pub use crate::data::clock::today;

/// The machine and run the report was measured on.
pub fn machine_line() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into());
    format!(
        "{cpu}, {cores} cores, load average {load} at start; {} build",
        if cfg!(debug_assertions) {
            "debug"
        } else {
            "release"
        }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quadrature_error_falls_with_order_and_default_is_accurate() {
        let k = knob_quadrature(true);
        let errs: Vec<f64> = k.points.iter().map(|p| p.error).collect();
        assert!(errs.windows(2).all(|w| w[1] <= w[0] * 1.01), "{errs:?}");
        let d = k.default_point().expect("default in sweep");
        assert!(d.error < 1e-5, "{}", d.error);
    }

    #[test]
    fn knee_picks_cheapest_adequate_point() {
        let k = Knob {
            id: "t".into(),
            title: "t".into(),
            metric: "m".into(),
            timed: "t".into(),
            reference: "r".into(),
            points: vec![
                Point {
                    setting: "a".into(),
                    value: 1.0,
                    error: 1e-2,
                    seconds: 1.0,
                    is_default: false,
                },
                Point {
                    setting: "b".into(),
                    value: 2.0,
                    error: 2e-6,
                    seconds: 2.0,
                    is_default: true,
                },
                Point {
                    setting: "c".into(),
                    value: 3.0,
                    error: 1e-6,
                    seconds: 9.0,
                    is_default: false,
                },
            ],
        };
        assert_eq!(knee(&k, 0.0).unwrap().setting, "b");
        assert_eq!(knee(&k, 0.05).unwrap().setting, "a");
    }
}
