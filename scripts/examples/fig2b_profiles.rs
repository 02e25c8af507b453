//! Paper Fig. 2b: line profiles Sx(x, y = 0, z = 0) of the 110 nm polystyrene reference bead
//! (n = 1.572 in water 1.333, λ = 1064 nm, w0 = 400 nm, NA 1.2) for
//! * `rayleigh` — the paper's model (suppl. S2): paraxial Gaussian focus, scalar dipole;
//! * `rayleigh_pol` — the same with the vector dipole field (`polarization` effect);
//! * `as_dipole` — angular-spectrum focused beam (truncated by the NA 1.2 aperture), point
//!   dipole (Mie amplitudes replaced by their dipole limit);
//! * `mie` — angular-spectrum beam, exact Lorenz–Mie sphere (interference term);
//! * `mie_full` — `mie` plus the |E_s|² term;
//!
//! and the focal fields |E|²/P along x and y (µm⁻²) of the paraxial Gaussian and of the
//! angular-spectrum beams, which explain the overshoot (docs/paper-figures.md, "Fig. 2b").
//! The angular-spectrum columns come for two beams: `w400`, a Gaussian spectrum of waist
//! parameter 400 nm (`Waist::Spectral`), and `fill`, the uniformly filled NA 1.2 aperture
//! (`Waist::SpectralNm(0.0)`), the tightest focus the objective makes (mean 1/e² radius 412 nm,
//! the closest to the paper's measured w0 ≈ 400 nm), both without the aplanatic factor (§9's
//! beams); and `vector`, the uniformly filled aplanatic focus (`Apodization::Aplanatic`, the
//! program's default beam since the one-beam work, docs/physics.md §10). None of the columns depends on
//! `Optics::default().beam`: each beam is built explicitly.
//!
//! Run: `cargo run --release --example fig2b_profiles -- [fig2b.png] > fig2b.csv` — CSV on
//! stdout, summary lines start with `#` (so the file stays loadable with
//! `numpy.loadtxt(..., comments="#")`); the figure (profiles normalised to their peaks) goes to
//! the path given, default `fig2b.png`.

use bfpscope::optics::mie::Complex64 as C64;
use bfpscope::optics::mie_beam::{
    optics_for_reach, Amplitudes, Apodization, MieBeam, MieBeamSpec, Waist,
};
use bfpscope::optics::params::{Optics, REF_BEAD_D_NM, REF_BEAD_N};
use bfpscope::optics::rayleigh::{alpha_um3, Detection, DetectorModel};
use bfpscope::plot::{plot_xy, Series, XyOpts};

/// Summary of an antisymmetric profile sampled on x ≥ 0: main peak, first sign change beyond
/// it, and the extremum of opposite sign (the "overshoot") beyond that.
fn describe(name: &str, xs: &[f64], s: &[f64]) -> String {
    let (mut ip, mut peak) = (0, 0.0f64);
    for (i, &v) in s.iter().enumerate() {
        if xs[i] >= 0.0 && v.abs() > peak.abs() {
            peak = v;
            ip = i;
        }
    }
    let mut zero = None;
    for i in ip..s.len() - 1 {
        if s[i].signum() != s[i + 1].signum() && s[i] != 0.0 {
            // linear interpolation of the crossing
            zero = Some(xs[i] - s[i] * (xs[i + 1] - xs[i]) / (s[i + 1] - s[i]));
            let (mut io, mut over) = (i + 1, 0.0f64);
            for (j, &v) in s.iter().enumerate().skip(i + 1) {
                if v.signum() != peak.signum() && v.abs() > over.abs() {
                    over = v;
                    io = j;
                }
                if v.signum() == peak.signum() && j > io + 2 {
                    break;
                }
            }
            return format!(
                "# {name:13} peak {peak:+.4e} at x = {:.3} µm; sign change at x = {:.3} µm; overshoot {over:+.3e} at x = {:.3} µm = {:+.2}% of the peak",
                xs[ip],
                zero.unwrap(),
                xs[io],
                100.0 * over / peak
            );
        }
    }
    let _ = zero;
    format!(
        "# {name:13} peak {peak:+.4e} at x = {:.3} µm; no sign change out to x = {:.2} µm (no overshoot)",
        xs[ip],
        xs[xs.len() - 1]
    )
}

struct Beam {
    tag: &'static str,
    mie: MieBeam,
    mie_full: MieBeam,
    dip: MieBeam,
}

fn main() {
    let o = Optics::default();
    let (d, n) = (REF_BEAD_D_NM, REF_BEAD_N);
    let alpha = alpha_um3(d, n, o.n_medium);
    let det = Detection::new(&o, &DetectorModel::default()).unwrap();
    let det_pol = Detection::new(
        &o,
        &DetectorModel {
            polarization: true,
            misalignment: None,
        },
    )
    .unwrap();
    // a grid converged well beyond the profile's ±1.5 µm (docs/physics.md §9)
    let om = optics_for_reach(&o, 2.0);
    let base = MieBeamSpec::for_reach(&om, 2.0, 0.5);
    let np = C64::new(n, 0.0);
    let beams: Vec<Beam> = [
        ("w400", Waist::Spectral, Apodization::None),
        ("fill", Waist::SpectralNm(0.0), Apodization::None),
        ("vector", Waist::SpectralNm(0.0), Apodization::Aplanatic),
    ]
    .into_iter()
    .map(|(tag, waist, apodization)| {
        let spec = MieBeamSpec {
            waist,
            apodization,
            ..base
        };
        Beam {
            tag,
            mie: MieBeam::new(&om, d, np, spec).unwrap(),
            mie_full: MieBeam::new(
                &om,
                d,
                np,
                MieBeamSpec {
                    scattered_intensity: true,
                    ..spec
                },
            )
            .unwrap(),
            dip: MieBeam::new(
                &om,
                d,
                np,
                MieBeamSpec {
                    amplitudes: Amplitudes::Dipole,
                    ..spec
                },
            )
            .unwrap(),
        }
    })
    .collect();
    let w0 = o.w0_um();
    let gauss_i =
        |r: f64| 2.0 / (std::f64::consts::PI * w0 * w0) * (-2.0 * r * r / (w0 * w0)).exp();

    let n_pts = 301;
    let xs: Vec<f64> = (0..n_pts)
        .map(|i| -1.5 + 3.0 * i as f64 / (n_pts - 1) as f64)
        .collect();
    println!(
        "# Fig. 2b: Sx(x, 0, 0) of a {d} nm bead, n = {n}, default optics (w0 = {} nm, NA {}); Mie tier grids (reach 2 µm): incident n_theta_in = {}, n_phi_in = {}, detection n_theta = {}, n_phi = {}",
        o.w0_nm, o.na, base.n_theta_in, base.n_phi_in, om.n_theta, om.n_phi
    );
    println!("# beams: w400 = Gaussian spectrum with w0 = 400 nm (Waist::Spectral); fill = uniformly filled NA 1.2 aperture (Waist::SpectralNm(0), the tightest focus); vector = the same aperture with the aplanatic 1/sqrt(cos theta) factor (Apodization::Aplanatic, the default beam)");
    let mut header = String::from("x_um,rayleigh,rayleigh_pol,I_gauss");
    for b in &beams {
        for c in ["as_dipole", "mie", "mie_full", "I_as_x", "I_as_y"] {
            header += &format!(",{c}_{}", b.tag);
        }
    }
    println!("{header}");
    let mut cols: Vec<(String, Vec<f64>)> = vec![
        ("rayleigh".into(), Vec::new()),
        ("rayleigh_pol".into(), Vec::new()),
    ];
    for b in &beams {
        for c in ["as_dipole", "mie", "mie_full"] {
            cols.push((format!("{c}_{}", b.tag), Vec::new()));
        }
    }
    for &x in &xs {
        let mut row = vec![
            alpha * det.response_unit(x, 0.0, 0.0).0[0],
            alpha * det_pol.response_unit(x, 0.0, 0.0).0[0],
        ];
        let mut line = format!("{x:.4},{:.6e},{:.6e},{:.6e}", row[0], row[1], gauss_i(x));
        for b in &beams {
            let v = [
                b.dip.response(x, 0.0, 0.0).unwrap()[0],
                b.mie.response(x, 0.0, 0.0).unwrap()[0],
                b.mie_full.response(x, 0.0, 0.0).unwrap()[0],
            ];
            row.extend(v);
            line += &format!(
                ",{:.6e},{:.6e},{:.6e},{:.6e},{:.6e}",
                v[0],
                v[1],
                v[2],
                b.mie.beam().intensity(x, 0.0, 0.0),
                b.mie.beam().intensity(0.0, x, 0.0)
            );
        }
        for (c, v) in cols.iter_mut().zip(row) {
            c.1.push(v);
        }
        println!("{line}");
    }
    for (name, c) in &cols {
        println!("{}", describe(name, &xs, c));
    }
    let png = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "fig2b.png".to_string());
    let label = |name: &str| match name {
        "rayleigh" => "Rayleigh, paraxial Gaussian (paper model)",
        "rayleigh_pol" => "Rayleigh + polarization",
        "mie_w400" => "Mie, Gaussian spectrum w0 = 400 nm",
        "mie_fill" => "Mie, filled NA 1.2 aperture",
        "as_dipole_fill" => "point dipole, filled aperture",
        "mie_vector" => "Mie, aplanatic vector focus (default beam)",
        _ => "",
    };
    let series: Vec<Series> = cols
        .iter()
        .filter(|(n, _)| !label(n).is_empty())
        .map(|(n, c)| {
            let peak = c.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            Series::line(label(n), xs.clone(), c.iter().map(|v| v / peak).collect())
        })
        .collect();
    plot_xy(
        &png,
        &series,
        &XyOpts::new(
            "Fig. 2b: Sx(x, y = 0) of a 110 nm polystyrene bead, normalised to its peak",
            "x (µm)",
            "Sx / peak",
        ),
    )
    .expect("write the figure");
    println!("# figure: {png}");
    let sens = |c: &[f64]| {
        let i = n_pts / 2;
        (c[i + 1] - c[i - 1]) / (xs[i + 1] - xs[i - 1])
    };
    let s_ray = sens(&cols[0].1);
    for (name, c) in &cols {
        println!(
            "# slope at x = 0: {name:15} {:.4e} µm⁻¹ = {:.3} × rayleigh",
            sens(c),
            sens(c) / s_ray
        );
    }
    // the focal field: first zero of Re Ex along x and y, and the ring beyond it
    let fine: Vec<f64> = (0..=600).map(|i| i as f64 * 0.0025).collect();
    for b in &beams {
        let bm = b.mie.beam();
        let e00 = bm.field(0.0, 0.0, 0.0)[0].re;
        let ex: Vec<f64> = fine
            .iter()
            .map(|&x| bm.field(x, 0.0, 0.0)[0].re / e00)
            .collect();
        let ey: Vec<f64> = fine
            .iter()
            .map(|&y| bm.field(0.0, y, 0.0)[0].re / e00)
            .collect();
        println!("{}", describe(&format!("Ex(x)_{}", b.tag), &fine, &ex));
        println!("{}", describe(&format!("Ex(y)_{}", b.tag), &fine, &ey));
        let (rx, ry) = bm.focal_radii();
        println!(
            "# focus {}: spectral waist {:.0} nm, I(0)/P = {:.4} µm⁻² (paraxial Gaussian w0 = 400 nm: {:.4}); 1/e² radius {:.1} nm along x (polarisation), {:.1} nm along y",
            b.tag,
            1e3 * bm.w_spec,
            bm.intensity(0.0, 0.0, 0.0),
            gauss_i(0.0),
            1e3 * rx,
            1e3 * ry
        );
    }
}
