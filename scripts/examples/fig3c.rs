//! Paper Fig. 3c: maximum sensitivity (∂Sx/∂x)max vs diameter for polystyrene beads
//! (n = 1.572 in water, default optics), maximised over the axial position z (x = y = 0), for
//! * `point` — Rayleigh point dipole (paper suppl. S2), ∝ d³ exactly;
//! * `finite` — finite-size Rayleigh (suppl. S6, `finite_size::max_sensitivity_unit`, sphere
//!   rule n_r = 8);
//! * `mie_w400` — angular-spectrum beam, Gaussian spectrum w0 = 400 nm, exact Mie, interference
//!   term only (as the Rayleigh models);
//! * `mief_w400` — the same plus the |E_s|² term;
//! * `mie_fill`, `mief_fill` — the uniformly filled NA 1.2 aperture (tightest focus, mean 1/e²
//!   radius 412 nm, closest to the paper's measured 400 nm);
//! * `fsas_w400`, `fsas_fill` — finite-size Rayleigh (volume average of point dipoles, suppl.
//!   S6) in the same angular-spectrum beams: the like-for-like partner of `mie_*` (Mie tends to
//!   it as m → 1, tests/mie_beam.rs), which separates Mie physics from the beam model.
//!
//! All curves normalised to 1 at 110 nm (as the paper); `dev0_*` is the departure from the
//! model's own small-particle limit (1 − S/S_{d→0}), `dev110_*` from the volume scaling
//! anchored at 110 nm (S/S(110)·(110/d)³ − 1, the paper's "scaling the bead maximum
//! sensitivity with volume"). Then the diameters where each model departs from d³ by 1% and 10%.
//!
//! Run: `cargo run --release --example fig3c -- [fig3c.png] > fig3c.csv` (CSV on stdout, `#`
//! summary lines; the log-log figure goes to the path given, default `fig3c.png`; about ten
//! minutes on one core, most of it in the `fsas_*` volume averages).
//!
//! Departure diameters: the table is computed once; a crossing is bracketed by the first table
//! diameter beyond the threshold and refined by 8 bisection steps on the model itself.

use bfpscope::optics::finite_size::{max_sensitivity_unit, sphere_points};
use bfpscope::optics::mie::Complex64 as C64;
use bfpscope::optics::mie_beam::{Amplitudes, MieBeam, MieBeamSpec, Waist};
use bfpscope::optics::params::{Optics, REF_BEAD_D_NM, REF_BEAD_N};
use bfpscope::optics::rayleigh::{alpha_um3, Detection, DetectorModel};
use bfpscope::plot::{plot_xy, Series, XyOpts};

const N_R: usize = 8;
/// Sphere rule for the finite-size model in the angular-spectrum beam (128 dipoles; n_r = 4 is
/// the knee of the `finite_size` accuracy knob).
const N_R_AS: usize = 4;

/// Maximise f over z ∈ [−0.5, 0.5] µm: 0.1 µm scan, then golden section on the best bracket
/// (the optimum of every model here lies within ±0.01 µm of the focus).
fn golden_max(f: impl Fn(f64) -> f64) -> (f64, f64) {
    let (mut best_z, mut best) = (0.0, f(0.0));
    for i in -5..=5 {
        let z = i as f64 * 0.1;
        let v = f(z);
        if v > best {
            best = v;
            best_z = z;
        }
    }
    let (mut a, mut b) = (best_z - 0.1, best_z + 0.1);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..25 {
        let (c, d) = (b - g * (b - a), a + g * (b - a));
        if f(c) > f(d) {
            b = d
        } else {
            a = c
        }
    }
    let z = 0.5 * (a + b);
    (f(z), z)
}

struct Model {
    name: &'static str,
    /// max sensitivity (µm⁻¹) and its z (µm) for diameter d (nm)
    f: Box<dyn Fn(f64) -> (f64, f64)>,
    /// small-particle limit per unit α (µm⁻⁴)
    limit_per_alpha: f64,
}

fn main() {
    let o = Optics::default();
    let n = REF_BEAD_N;
    let np = C64::new(n, 0.0);
    let alpha = move |d: f64| alpha_um3(d, n, 1.333);
    let det = Detection::new(&o, &DetectorModel::default()).unwrap();
    let (point_unit, _) = max_sensitivity_unit(&det, None, N_R);
    let mut models: Vec<Model> = Vec::new();
    {
        let det = det.clone();
        models.push(Model {
            name: "finite",
            f: Box::new(move |d| {
                let (s, z) = max_sensitivity_unit(&det, Some(d), N_R);
                (s * alpha(d), z)
            }),
            limit_per_alpha: point_unit,
        });
    }
    for (tag, waist) in [("w400", Waist::Spectral), ("fill", Waist::SpectralNm(0.0))] {
        let base = MieBeamSpec {
            waist,
            ..MieBeamSpec::default()
        };
        let dip = MieBeam::new(
            &o,
            10.0,
            np,
            MieBeamSpec {
                amplitudes: Amplitudes::Dipole,
                ..base
            },
        )
        .unwrap();
        let lim = dip.max_sensitivity_x().0 / alpha(10.0);
        // finite-size Rayleigh in the same angular-spectrum beam: the volume average of the
        // dipole-limit response (suppl. S6 construction), which Mie approaches as m → 1
        let o3 = o.clone();
        models.push(Model {
            name: if tag == "w400" {
                "fsas_w400"
            } else {
                "fsas_fill"
            },
            f: Box::new(move |d| {
                let dip = MieBeam::new(
                    &o3,
                    d,
                    np,
                    MieBeamSpec {
                        amplitudes: Amplitudes::Dipole,
                        ..base
                    },
                )
                .unwrap();
                let pts = sphere_points(d * 1e-3, N_R_AS);
                golden_max(|z| {
                    pts.iter()
                        .map(|(p, w)| w * dip.response_grad(p[0], p[1], p[2] + z).unwrap().1[0])
                        .sum()
                })
            }),
            limit_per_alpha: lim,
        });
        for full in [false, true] {
            let o2 = o.clone();
            let spec = MieBeamSpec {
                scattered_intensity: full,
                ..base
            };
            models.push(Model {
                name: match (tag, full) {
                    ("w400", false) => "mie_w400",
                    ("w400", true) => "mief_w400",
                    (_, false) => "mie_fill",
                    _ => "mief_fill",
                },
                f: Box::new(move |d| MieBeam::new(&o2, d, np, spec).unwrap().max_sensitivity_x()),
                limit_per_alpha: lim,
            });
        }
    }

    let png = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "fig3c.png".to_string());
    let mut ds: Vec<f64> = (0..25)
        .map(|i| 50.0 * 20f64.powf(i as f64 / 24.0))
        .collect();
    ds.extend([REF_BEAD_D_NM, 160.0, 240.0, 500.0]);
    ds.sort_by(|a, b| a.total_cmp(b));
    ds.dedup();

    println!("# Fig. 3c: (dSx/dx)max vs diameter, polystyrene n = {n}, water, λ = 1064 nm, w0 = 400 nm, NA 1.2; maximised over z at x = y = 0");
    let refs: Vec<f64> = models.iter().map(|m| (m.f)(REF_BEAD_D_NM).0).collect();
    let ref_point = point_unit * alpha(REF_BEAD_D_NM);
    let mut header = String::from("d_nm,point");
    for m in &models {
        header += &format!(",{0},dev0_{0},dev110_{0},zopt_um_{0}", m.name);
    }
    println!("{header}");
    // table[model][i] = (d, S/S110)
    let mut table: Vec<Vec<f64>> = vec![Vec::new(); models.len()];
    for &d in &ds {
        let mut line = format!("{d:.2},{:.6e}", point_unit * alpha(d) / ref_point);
        for ((m, &r), col) in models.iter().zip(&refs).zip(table.iter_mut()) {
            let (s, z) = (m.f)(d);
            let dev0 = 1.0 - s / (m.limit_per_alpha * alpha(d));
            let dev110 = s / r * (REF_BEAD_D_NM / d).powi(3) - 1.0;
            line += &format!(",{:.6e},{dev0:.5},{dev110:.5},{z:.4}", s / r);
            col.push(s / r);
        }
        println!("{line}");
    }
    // absolute numbers at 110 nm
    println!(
        "# absolute (dSx/dx)max at 110 nm (µm⁻¹): point {:.5e}{}",
        ref_point,
        models
            .iter()
            .zip(&refs)
            .map(|(m, r)| format!(", {} {:.5e}", m.name, r))
            .collect::<String>()
    );
    // departure diameters: bracket from the table, bisection on the model
    for ((m, &r), col) in models.iter().zip(&refs).zip(&table) {
        let dev0 = |d: f64, s_rel: f64| 1.0 - s_rel * r / (m.limit_per_alpha * alpha(d));
        let dev110 = |d: f64, s_rel: f64| s_rel * (REF_BEAD_D_NM / d).powi(3) - 1.0;
        let cross = |g: &dyn Fn(f64, f64) -> f64, t: f64, lo: f64| -> Option<f64> {
            let mut prev = lo;
            for (&d, &v) in ds.iter().zip(col) {
                if d <= lo {
                    continue;
                }
                if g(d, v).abs() > t {
                    let (mut a, mut b) = (prev, d);
                    for _ in 0..8 {
                        let c = 0.5 * (a + b);
                        if g(c, (m.f)(c).0 / r).abs() > t {
                            b = c
                        } else {
                            a = c
                        }
                    }
                    return Some(0.5 * (a + b));
                }
                prev = d;
            }
            None
        };
        let fmt = |v: Option<f64>| v.map_or("> 1000".to_string(), |d| format!("{d:.0}"));
        println!(
            "# {:10} departs from its d→0 limit by 1% at d = {} nm, by 10% at d = {} nm; from the 110-nm-anchored d³ (going up from 110 nm) by 1% at d = {} nm, by 10% at d = {} nm (at 50 nm: dev0 = {:+.4}, dev110 = {:+.4}; at 240 nm: dev110 = {:+.4})",
            m.name,
            fmt(cross(&dev0, 0.01, 5.0)),
            fmt(cross(&dev0, 0.10, 5.0)),
            fmt(cross(&dev110, 0.01, REF_BEAD_D_NM)),
            fmt(cross(&dev110, 0.10, REF_BEAD_D_NM)),
            dev0(ds[0], col[0]),
            dev110(ds[0], col[0]),
            dev110(240.0, col[ds.iter().position(|&d| d == 240.0).unwrap()]),
        );
    }
    // the figure: one log-log plot, all curves normalised at 110 nm
    let pick = |name: &str| table[models.iter().position(|m| m.name == name).unwrap()].clone();
    let series = vec![
        Series::line(
            "Rayleigh point dipole (suppl. S2): d³",
            ds.clone(),
            ds.iter().map(|&d| (d / REF_BEAD_D_NM).powi(3)).collect(),
        ),
        Series::line(
            "finite-size Rayleigh (suppl. S6, paraxial beam)",
            ds.clone(),
            pick("finite"),
        ),
        Series::line(
            "finite-size Rayleigh, filled-aperture beam",
            ds.clone(),
            pick("fsas_fill"),
        ),
        Series::line(
            "Mie, Gaussian spectrum w0 = 400 nm",
            ds.clone(),
            pick("mie_w400"),
        ),
        Series::line("Mie, filled NA 1.2 aperture", ds.clone(), pick("mie_fill")),
        Series::line(
            "Mie + |E_s|², filled aperture",
            ds.clone(),
            pick("mief_fill"),
        ),
    ];
    plot_xy(
        &png,
        &series,
        &XyOpts::new(
            "Fig. 3c: max sensitivity vs bead diameter (polystyrene in water, 1064 nm, NA 1.2)",
            "bead diameter (nm)",
            "(∂Sx/∂x)max / value at 110 nm",
        )
        .log_log(),
    )
    .expect("write the figure");
    println!("# figure: {png}");
}
