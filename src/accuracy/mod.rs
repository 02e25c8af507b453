//! What accuracy costs in time: for each approximation knob, sweep its values and
//! measure, in one run on this machine, the error against a high-accuracy reference computed in
//! the same run and the time spent (median of repeats). `bfpscope accuracy` writes the tables and
//! Pareto plots to docs/accuracy.md.

pub mod analysis_knobs;
pub mod instrument;
pub mod mie_knobs;
pub mod report;
pub mod sweep;

use crate::instrument::sim::scene::{DiameterProfile, Filament, Scene};
use crate::instrument::sim::{render_xy, Renderer};
use crate::optics::finite_size::max_sensitivity_unit;
use crate::optics::grid::Interp;
use crate::optics::mie::Complex64 as C64;
use crate::optics::mie_beam::{optics_for_reach, Amplitudes, MieBeam, MieBeamSpec};
use crate::optics::mie_template::{MieTemplate, MieTemplateSpec, DIPOLE_D_NM, DIPOLE_N};
use crate::optics::params::Beam;
use crate::optics::params::Optics;
use crate::optics::rayleigh::alpha_um3;
use crate::optics::rayleigh::{Detection, DetectorModel};
use crate::optics::template::{ModelTemplate, TemplateSpec};
use crate::optics::ValidOptics;
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

/// Detection quadrature of the default (vector) beam: `optics.n_theta`, `optics.n_phi` set the
/// detection grid of every direct vector-beam evaluation (`MieBeam` with
/// `MieBeamSpec::of_beam`: the scene's domain check, `max_sensitivity_in_beam`, the model
/// calibrations) and are the floor of the grid the simulator's templates use
/// (`mie_beam::optics_for_reach` raises it to the reach each plane needs). Error: worst error of
/// (Sx, Sy, Sz) of the vector beam's point dipole (`Amplitudes::Dipole`, per unit α) over the 7
/// test points relative to the peak Sx, against a (96, 48) rule (incident grid resolving the
/// points' reach in every case); time of one response evaluation (Sx, Sy, Sz).
pub fn knob_quadrature(quick: bool) -> Knob {
    vector_quadrature_sweep(
        quick,
        DetectorModel::default(),
        "quadrature",
        "Quadrature order over the detection cone (vector beam)",
    )
}

/// The vector-beam sweep with the `misalignment` effect: the QPD's sign boundaries no longer
/// fall on rule boundaries, so convergence is algebraic.
pub fn knob_quadrature_misaligned(quick: bool) -> Knob {
    vector_quadrature_sweep(
        quick,
        misaligned(),
        "quadrature_misaligned",
        "Quadrature order, misaligned QPD (vector beam)",
    )
}

/// The paraxial detection quadrature (`Detection::new`, the paper's model,
/// `set_optics(#{beam: "paraxial"})`): worst error of (Sx, Sy, Sz) over the test points
/// relative to the peak Sx against a (128, 64) rule; time of one response evaluation.
pub fn knob_quadrature_paraxial(quick: bool) -> Knob {
    quadrature_sweep(
        quick,
        DetectorModel::default(),
        "quadrature_paraxial",
        "Quadrature order over the detection cone (paraxial)",
    )
}

/// [`knob_quadrature_paraxial`] with a misaligned QPD.
pub fn knob_quadrature_misaligned_paraxial(quick: bool) -> Knob {
    quadrature_sweep(
        quick,
        misaligned(),
        "quadrature_misaligned_paraxial",
        "Quadrature order, misaligned QPD (paraxial)",
    )
}

fn misaligned() -> DetectorModel {
    DetectorModel {
        polarization: false,
        misalignment: Some(Default::default()),
    }
}

/// The vector beam's point dipole (a [`DIPOLE_D_NM`] sphere's exact dipole amplitudes) with
/// detection grid (`n_theta`, `n_phi`) and an incident grid resolving ρ ≤ `reach_um`, |z| ≤
/// `z_um`; responses are divided by its polarisability (per unit α, µm⁻³).
pub fn vector_dipole(
    o: &Optics,
    n_theta: usize,
    n_phi: usize,
    model: DetectorModel,
    reach_um: f64,
    z_um: f64,
) -> (MieBeam, f64) {
    let o = ValidOptics::new(Optics {
        n_theta,
        n_phi,
        beam: Beam::Vector,
        ..o.clone()
    })
    .expect("valid optics");
    let spec = MieBeamSpec {
        amplitudes: Amplitudes::Dipole,
        detector: model,
        ..MieBeamSpec::for_reach(&o, reach_um, z_um).with_beam_of(&o)
    };
    let mb = MieBeam::new(&o, DIPOLE_D_NM, C64::new(DIPOLE_N, 0.0), spec).expect("valid optics");
    (mb, alpha_um3(DIPOLE_D_NM, DIPOLE_N, o.n_medium))
}

/// Reference detection order of the vector quadrature sweeps: (96, 48) × the incident grid for
/// the test points is 7.1e6 pairs, within `mie_beam::MAX_PAIRS`.
pub const VECTOR_QUAD_REF: (usize, usize) = (96, 48);

fn vector_quadrature_sweep(quick: bool, model: DetectorModel, id: &str, title: &str) -> Knob {
    let base = Optics::default();
    let pts = test_points();
    let reach = pts.iter().map(|p| p.0.hypot(p.1)).fold(0.0, f64::max) + 0.05;
    let zmax = pts.iter().map(|p| p.2.abs()).fold(0.0, f64::max);
    let (rt, rp) = VECTOR_QUAD_REF;
    let (r, a0) = vector_dipole(&base, rt, rp, model, reach, zmax);
    let peak = r.response_unchecked(0.25, 0.0, 0.0)[0].abs() / a0;
    let text = [
        id,
        title,
        "worst |ΔS| of the vector beam's point dipole over 7 points out to (2, 1, 1.5) µm, relative to peak Sx",
        "one point response (Sx, Sy, Sz), incident grid fixed",
    ];
    quadrature_knob(
        quick,
        &base,
        text,
        format!("Gauss–Legendre ({rt}, {rp})"),
        |nt| {
            let (d, _) = vector_dipole(&base, nt, nt / 2, model, reach, zmax);
            let o = Optics {
                n_theta: nt,
                n_phi: nt / 2,
                ..base.clone()
            };
            let det_reach = ((nt.min(2 * (nt / 2))) as f64 - 8.0).max(0.0)
                / (0.75 * o.k_per_um() * o.theta_max().sin());
            // worst over all points, and over those within the grid's reach (where
            // `MieBeam::response` answers; beyond it, it refuses)
            let (mut worst, mut worst_in): (f64, f64) = (0.0, 0.0);
            let mut n_in = 0;
            for &(x, y, z) in &pts {
                let (a, b) = (d.response_unchecked(x, y, z), r.response_unchecked(x, y, z));
                let inside = x.hypot(y) <= det_reach;
                n_in += inside as usize;
                for c in 0..3 {
                    let e = (a[c] - b[c]).abs() / a0 / peak;
                    worst = worst.max(e);
                    if inside {
                        worst_in = worst_in.max(e);
                    }
                }
            }
            let secs = time_median(if quick { 5 } else { 21 }, || {
                d.response_unchecked(0.31, -0.12, 0.05)
            });
            let setting = format!(
                "n_theta = {nt}, n_phi = {} (reach ρ ≤ {det_reach:.2} µm; {n_in} of {} points inside{})",
                nt / 2,
                pts.len(),
                if n_in > 0 {
                    format!(", worst there {worst_in:.1e}")
                } else {
                    String::new()
                }
            );
            (setting, worst, secs)
        },
    )
}

/// A quadrature sweep's knob (`text`: id, title, metric, what is timed): each detection order
/// n_theta = nt, n_phi = nt/2 (4·nt·(nt/2) nodes) of the sweep (fewer when `quick`), measured
/// by `at(nt)` → (setting, worst error, time in s); the error is floored at 1e-16 for the log
/// axis.
fn quadrature_knob(
    quick: bool,
    base: &Optics,
    [id, title, metric, timed]: [&str; 4],
    reference: String,
    mut at: impl FnMut(usize) -> (String, f64, f64),
) -> Knob {
    let orders: &[usize] = if quick {
        &[8, 16, 24, 48]
    } else {
        &[6, 8, 12, 16, 24, 32, 48, 64]
    };
    let points = orders
        .iter()
        .map(|&nt| {
            let (setting, worst, secs) = at(nt);
            Point {
                setting,
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
        metric: metric.into(),
        timed: timed.into(),
        reference,
        points,
    }
}

fn quadrature_sweep(quick: bool, model: DetectorModel, id: &str, title: &str) -> Knob {
    let base = Optics {
        beam: Beam::Paraxial,
        ..Optics::default()
    };
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
    let pts = test_points();
    let text = [
        id,
        title,
        "worst |ΔS| over 7 points out to (2, 1, 1.5) µm, relative to peak Sx",
        "one point response (Sx, Sy, Sz and x/y derivatives)",
    ];
    let reference = "Gauss–Legendre (128, 64)".to_string();
    quadrature_knob(quick, &base, text, reference, |nt| {
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
        (format!("n_theta = {nt}, n_phi = {}", nt / 2), worst, secs)
    })
}

/// Template grid spacing and interpolation of the default (vector) beam: the simulator's
/// point-dipole template (`MieTemplate::point_dipole`, band-limited planes) evaluated on a
/// 64×64 grid at an off-plane height (z = 0.137 µm, so z is interpolated too), RMS error of Sx
/// against the direct vector-beam response at every pixel (`MieBeam`, `Amplitudes::Dipole`,
/// detection and incident grids resolving 3 µm: finer than the planes' own), relative to the
/// peak; time to build the template planes and evaluate the image.
pub fn knob_template(quick: bool) -> Knob {
    let o = Optics::default();
    let z = 0.137;
    let n = if quick { 32 } else { 64 };
    let xs: Vec<f64> = (0..n)
        .map(|i| -1.0 + 2.0 * i as f64 / (n - 1) as f64)
        .collect();
    let fine = optics_for_reach(&o, TEMPLATE_REF_REACH_UM);
    let (direct, a0) = vector_dipole(
        &o,
        fine.n_theta,
        fine.n_phi,
        DetectorModel::default(),
        TEMPLATE_REF_REACH_UM,
        z,
    );
    let mut truth = vec![];
    for &y in &xs {
        for &x in &xs {
            truth.push(direct.response_unchecked(x, y, z)[0] / a0);
        }
    }
    let points = template_points(quick, &xs, &truth, &|spec| {
        let mspec = MieTemplateSpec {
            grid: spec,
            detector: DetectorModel::default(),
            scattered_intensity: false,
        };
        let t = MieTemplate::point_dipole(&o, mspec).expect("default optics");
        Box::new(move |x, y| t.eval(x, y, z).expect("inside the planes")[0])
    });
    Knob {
        id: "template".into(),
        title: "Template grid spacing h and interpolation, vector beam (hz = 50 nm)".into(),
        metric: format!("RMS error of a {n}×{n} Sx image of the point dipole at z = 0.137 µm, relative to its peak"),
        timed: "build the vector-beam template planes + evaluate the image".into(),
        reference: format!("direct vector-beam response at every pixel (grids resolving ρ ≤ {TEMPLATE_REF_REACH_UM} µm)"),
        points,
    }
}

/// An image's Sx at (x, y) from one template.
type TemplateImage = Box<dyn Fn(f64, f64) -> f64>;

/// The template knobs' sweep: for each interpolation and spacing h (hz = 50 nm), `build(spec)`
/// makes the template, which is evaluated on `xs` × `xs` (rows y) against `truth`; error = RMS /
/// peak of `truth`, time = build + evaluation (median).
fn template_points(
    quick: bool,
    xs: &[f64],
    truth: &[f64],
    build: &dyn Fn(TemplateSpec) -> TemplateImage,
) -> Vec<Point> {
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
                let t = build(spec);
                let mut s2 = 0.0;
                let mut k = 0;
                for &y in xs {
                    for &x in xs {
                        s2 += (t(x, y) - truth[k]).powi(2);
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
    points
}

/// Reach (µm) of the direct reference of [`knob_template`]: twice the focal plane's support.
pub const TEMPLATE_REF_REACH_UM: f64 = 3.0;

/// The same sweep in the paper's paraxial beam (`set_optics(#{beam: "paraxial"})`): the
/// `ModelTemplate` of the paraxial detection cone, RMS error of a 64×64 image of a 110 nm bead
/// at z = 0.137 µm against direct evaluation, relative to the peak; time to build the template
/// planes and render the image.
pub fn knob_template_paraxial(quick: bool) -> Knob {
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
    let points = template_points(quick, &xs, &truth, &|spec| {
        let t = ModelTemplate::new(det.clone(), spec).unwrap();
        Box::new(move |x, y| t.eval(x, y, z)[0])
    });
    Knob {
        id: "template_paraxial".into(),
        title: "Template grid spacing h and interpolation, paraxial (hz = 50 nm)".into(),
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

/// Finite-size sphere rule order (suppl. S6) in the default (vector) beam: ∂Sx/∂x of a 500 nm
/// bead at its centre, z = 0, as the simulator renders the `finite_size` effect there (the
/// rule's dipoles, each the vector beam's point dipole: `MieBeam` with `Amplitudes::Dipole`,
/// default grids), relative error against n_r = 14; time of one sensitivity evaluation.
pub fn knob_finite_size(quick: bool) -> Knob {
    let o = ValidOptics::default();
    let spec = MieBeamSpec {
        amplitudes: Amplitudes::Dipole,
        ..MieBeamSpec::of_beam(&o)
    };
    let dip = MieBeam::new(&o, DIPOLE_D_NM, C64::new(DIPOLE_N, 0.0), spec).expect("default optics");
    let d = 500.0;
    let at0 = |n_r: usize| -> f64 {
        crate::optics::finite_size::sphere_points(d * 1e-3, n_r)
            .iter()
            .map(|(p, w)| w * dip.response_grad(p[0], p[1], p[2]).expect("within reach").1[0])
            .sum()
    };
    let points = sphere_rule_points(quick, &at0);
    Knob {
        id: "finite_size".into(),
        title: "Finite-size sphere rule (suppl. S6), 500 nm bead, vector beam".into(),
        metric: "relative error of ∂Sx/∂x at the bead centre, z = 0".into(),
        timed:
            "one sensitivity evaluation of the decomposed sphere (direct point-dipole responses)"
                .into(),
        reference: "n_r = 14 (5488 dipoles)".into(),
        points,
    }
}

/// The finite-size knobs' sweep: `at0(n_r)` at the radial orders of the sweep against n_r = 14.
fn sphere_rule_points(quick: bool, at0: &dyn Fn(usize) -> f64) -> Vec<Point> {
    let reference = at0(14);
    let orders: &[usize] = if quick {
        &[1, 2, 4, 6]
    } else {
        &[1, 2, 3, 4, 6, 9]
    };
    orders
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
        .collect()
}

/// [`knob_finite_size`] in the paper's paraxial beam (`Detection::response_unit`).
pub fn knob_finite_size_paraxial(quick: bool) -> Knob {
    let det = Detection::new(&Optics::default(), &DetectorModel::default()).unwrap();
    let d = 500.0;
    let at0 = |n_r: usize| bfpscope_fs_sens(&det, d, n_r);
    let points = sphere_rule_points(quick, &at0);
    let _ = max_sensitivity_unit; // the full focus search uses the same rule
    Knob {
        id: "finite_size_paraxial".into(),
        title: "Finite-size sphere rule (suppl. S6), 500 nm bead, paraxial".into(),
        metric: "relative error of ∂Sx/∂x at the bead centre, z = 0".into(),
        timed: "one sensitivity evaluation of the decomposed sphere".into(),
        reference: "n_r = 14 (5488 dipoles)".into(),
        points,
    }
}

fn bfpscope_fs_sens(det: &Detection, d_nm: f64, n_r: usize) -> f64 {
    crate::optics::finite_size::response_unit_finite(det, d_nm, n_r, 0.0, 0.0, 0.0).1[0]
}

/// What the paper's approximation costs: the paraxial scalar Gaussian of
/// suppl. S3 against the default instrument, the aplanatic vector focus of a uniformly filled
/// NA 1.2 objective (validated against an independent Richards–Wolf model, docs/physics.md §10).
/// Error: RMS of an n×n Sx image of a 110 nm polystyrene bead relative to the vector beam's
/// peak; time: build the renderer (templates from scratch) and render the image.
pub fn knob_beam(quick: bool) -> Knob {
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
        knob_quadrature_paraxial(quick),
        knob_quadrature_misaligned_paraxial(quick),
        knob_template(quick),
        knob_template_paraxial(quick),
        knob_bead_spacing(quick),
        knob_finite_size(quick),
        knob_finite_size_paraxial(quick),
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
    fmt_scaled(
        s,
        &[
            (1e-6, 1e9, 0, "ns"),
            (1e-3, 1e6, 1, "µs"),
            (1.0, 1e3, 1, "ms"),
        ],
    )
}

/// A time `s` (s) in the unit of the first row `(below, per second, decimals, unit)` whose
/// bound it is below, else in s with two decimals.
fn fmt_scaled(s: f64, rows: &[(f64, f64, usize, &str)]) -> String {
    match rows.iter().find(|r| s < r.0) {
        Some(&(_, per_s, decimals, unit)) => format!("{:.decimals$} {unit}", s * per_s),
        None => format!("{s:.2} s"),
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
    fn times_are_written_in_the_unit_of_their_range() {
        let secs: Vec<String> = [4.2e-7, 3.14e-5, 0.0123, 2.5, f64::NAN]
            .map(fmt_secs)
            .into();
        assert_eq!(secs, ["420 ns", "31.4 µs", "12.3 ms", "2.50 s", "NaN s"]);
        let dwells: Vec<String> = [2e-4, 5e-3, 0.02, 1.5].map(instrument::fmt_dwell).into();
        assert_eq!(dwells, ["200 µs", "5.0 ms", "20 ms", "1.50 s"]);
    }

    #[test]
    fn quadrature_error_falls_with_order_and_default_is_accurate() {
        let k = knob_quadrature_paraxial(true);
        let errs: Vec<f64> = k.points.iter().map(|p| p.error).collect();
        assert!(errs.windows(2).all(|w| w[1] <= w[0] * 1.01), "{errs:?}");
        let d = k.default_point().expect("default in sweep");
        assert!(d.error < 1e-5, "{}", d.error);
    }

    /// The vector-beam detection quadrature's reference path: (48, 24) agrees with the (96, 48)
    /// reference to 1e-12 of the peak over the 7 test points (the knob measured 3.2e-15), so
    /// the reference is converged; the default (16, 8) is within the 3e-5 criterion at the test
    /// points inside its reach (ρ ≤ 1.51 µm), and beyond it (2.24 µm) off by more than 1e-4
    /// (the knob measured 3.6e-4): that is the documented "below the knee".
    #[test]
    fn vector_quadrature_reference_is_converged_and_default_holds_within_its_reach() {
        let o = Optics::default();
        let pts = test_points();
        let m = DetectorModel::default();
        let (r, a0) = vector_dipole(&o, VECTOR_QUAD_REF.0, VECTOR_QUAD_REF.1, m, 2.3, 1.5);
        let peak = r.response_unchecked(0.25, 0.0, 0.0)[0].abs();
        assert!(peak / a0 > 1e-3, "{}", peak / a0);
        let worst = |nt: usize, within: f64| -> f64 {
            let (d, _) = vector_dipole(&o, nt, nt / 2, m, 2.3, 1.5);
            let mut w: f64 = 0.0;
            for &(x, y, z) in pts.iter().filter(|p| p.0.hypot(p.1) <= within) {
                let (a, b) = (d.response_unchecked(x, y, z), r.response_unchecked(x, y, z));
                for c in 0..3 {
                    w = w.max((a[c] - b[c]).abs() / peak);
                }
            }
            w
        };
        assert!(worst(48, 10.0) < 1e-12, "{}", worst(48, 10.0));
        assert!(worst(16, 1.51) < 3e-5, "{}", worst(16, 1.51));
        assert!(worst(16, 10.0) > 1e-4, "{}", worst(16, 10.0));
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
