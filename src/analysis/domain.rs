//! Every estimator states its domain: the conditions under which its number and its σ hold.
//!
//! An answer carries `warnings`, plain-language sentences, empty when the answer is inside its
//! domain; its `status` is `"ok"` only then ([`status`]). A condition that makes the number
//! meaningless is a refusal (an [`super::AnalysisError`]), not a warning. The conditions of each
//! estimator are listed in `docs/analysis.md` ("Domains"); the shared checks live here:
//!
//! - the point-dipole template's size domain ([`dipole_d_max_nm`]), from the focused-beam Mie
//!   tier's comparison with the point dipole (`optics::mie_beam::point_dipole_error`, the
//!   simulator's domain check `instrument::sim::domain`);
//! - the pixel noise of an image measured from the data themselves ([`pixel_noise`]);
//! - the object whole inside the scan ([`margin_warning`]).

use crate::data::Image;

/// `"ok"` when there is no warning, else `"flagged"`.
pub fn status(warnings: &[String]) -> &'static str {
    if warnings.is_empty() {
        "ok"
    } else {
        "flagged"
    }
}

/// Robust pixel noise of an image, in its units: 1.4826·MAD of the first differences along
/// its rows (or columns), divided by √2. An object's smooth signal barely moves the median of
/// the differences, so this is the noise of one pixel, not the signal's spread. 0 when the
/// image has fewer than two finite neighbours in a line.
pub fn pixel_noise(img: &Image, rows: bool) -> f64 {
    let mut diffs = Vec::with_capacity(img.data.len());
    let axis = if rows {
        ndarray::Axis(0)
    } else {
        ndarray::Axis(1)
    };
    for lane in img.data.axis_iter(axis) {
        diffs.extend(
            lane.windows(2)
                .into_iter()
                .map(|w| w[1] - w[0])
                .filter(|d| d.is_finite()),
        );
    }
    super::stats::robust_std(&diffs).unwrap_or(0.0) / std::f64::consts::SQRT_2
}

/// Diameters (nm) at which the point dipole's maximum sensitivity per polarisability departs by
/// 1 % from the focused-beam Mie sphere's, relative to the 110 nm polystyrene reference, in the
/// paper's beam (1064 nm in water, λ/n_medium = 798 nm), by index: the crossings that
/// `instrument::sim::domain::is_suspect` documents (polystyrene between 190 and 200 nm, silica
/// 1.45 between 100 and 110 nm, n = 1.35 from 60 nm, n = 2 between 50 and 60 nm, n = 4–5 between
/// 20 and 30 nm), taken at their lower ends. Linear in n between the rows.
const DIPOLE_CROSSINGS: [(f64, f64); 6] = [
    (1.35, 60.0),
    (1.45, 100.0),
    (1.572, 190.0),
    (2.0, 50.0),
    (4.0, 20.0),
    (5.0, 20.0),
];

/// λ/n_medium (nm) of the beam in which [`DIPOLE_CROSSINGS`] were measured.
const CROSSINGS_LAMBDA_MEDIUM_NM: f64 = 1064.0 / 1.333;

/// Largest diameter (nm) of a sphere of index `n` for which the point-dipole template (and the
/// weight → volume conversion of eq. nCor) holds within 1 % (see [`DIPOLE_CROSSINGS`]), scaled
/// with the wavelength in the medium (the error depends on d/λ_medium).
pub fn dipole_d_max_nm(n: f64, wavelength_nm: f64, n_medium: f64) -> f64 {
    let t = &DIPOLE_CROSSINGS;
    let d = if n <= t[0].0 {
        t[0].1
    } else if n >= t[t.len() - 1].0 {
        t[t.len() - 1].1
    } else {
        let i = t
            .iter()
            .position(|r| r.0 >= n)
            .unwrap_or(t.len() - 1)
            .max(1);
        let (a, b) = (t[i - 1], t[i]);
        a.1 + (b.1 - a.1) * (n - a.0) / (b.0 - a.0)
    };
    d * (wavelength_nm / n_medium) / CROSSINGS_LAMBDA_MEDIUM_NM
}

/// A warning when the point (x, y) (µm) lies closer than `margin_um` to the edge of the scanned
/// area of `img` (or outside it): the object is then not whole inside the scan.
pub fn margin_warning(what: &str, img: &Image, x: f64, y: f64, margin_um: f64) -> Option<String> {
    margin_warning_in(what, span(&img.x), span(&img.y), x, y, margin_um)
}

/// [`margin_warning`] against the area x ∈ `xs`, y ∈ `ys` (µm): the part of an image that holds
/// data (a derivative image's outer columns hold none).
pub fn margin_warning_in(
    what: &str,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
    x: f64,
    y: f64,
    margin_um: f64,
) -> Option<String> {
    let d = (x - x0).min(x1 - x).min(y - y0).min(y1 - y);
    (d < margin_um).then(|| {
        format!(
            "{what} at ({x:.3}, {y:.3}) µm is {} of the scan's edge (needs ≥ {margin_um:.2} µm inside the area with data x ∈ [{x0:.3}, {x1:.3}], y ∈ [{y0:.3}, {y1:.3}] µm to be whole inside it)",
            if d < 0.0 {
                "outside".to_string()
            } else {
                format!("{d:.3} µm")
            }
        )
    })
}

fn span(v: &[f64]) -> (f64, f64) {
    let a = v.first().copied().unwrap_or(0.0);
    let b = v.last().copied().unwrap_or(0.0);
    (a.min(b), a.max(b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::mie_beam::point_dipole_error;
    use crate::optics::params::Optics;

    #[test]
    fn status_is_ok_only_without_warnings() {
        assert_eq!(status(&[]), "ok");
        assert_eq!(status(&["x".to_string()]), "flagged");
    }

    #[test]
    fn dipole_domain_edges_agree_with_the_mie_tier() {
        // Inside the table's edge the point dipole is within 1 % of the Mie tier, well beyond it
        // it is not (polystyrene, the paper's beam): the table is the Mie tier's, not a guess.
        let o = Optics::default();
        let dmax = dipole_d_max_nm(1.572, o.wavelength_nm, o.n_medium);
        assert!((dmax - 190.0 * (o.wavelength_nm / o.n_medium) / (1064.0 / 1.333)).abs() < 1e-9);
        let inside = point_dipole_error(&o, dmax - 10.0, 1.572).unwrap();
        let outside = point_dipole_error(&o, 300.0, 1.572).unwrap();
        assert!(inside.abs() < 0.01, "inside: {inside}");
        assert!(outside.abs() > 0.02, "outside: {outside}");
        // twice the wavelength in the medium: twice the diameter
        assert!((dipole_d_max_nm(1.572, 2.0 * 1064.0, 1.333) - 380.0).abs() < 1e-9);
        // between rows: linear
        assert!((dipole_d_max_nm(1.5, 1064.0, 1.333) - (100.0 + 90.0 * 0.05 / 0.122)).abs() < 1e-9);
    }

    #[test]
    fn margin_warns_near_and_outside_the_edge_only() {
        let img = Image::new(
            ndarray::Array2::zeros((11, 11)),
            (0..11).map(|i| i as f64 * 0.1).collect(),
            (0..11).map(|i| i as f64 * 0.1).collect(),
        );
        assert!(margin_warning("bead", &img, 0.5, 0.5, 0.3).is_none());
        let w = margin_warning("bead", &img, 0.9, 0.5, 0.3).unwrap();
        assert!(w.contains("0.100 µm of the scan's edge"), "{w}");
        let w = margin_warning("bead", &img, 1.2, 0.5, 0.3).unwrap();
        assert!(w.contains("outside of the scan's edge"), "{w}");
    }

    #[test]
    fn pixel_noise_of_white_noise_is_its_sigma_and_ignores_a_smooth_signal() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let nd = Normal::new(0.0, 0.3).unwrap();
        let n = 100;
        let data = ndarray::Array2::from_shape_fn((n, n), |(r, c)| {
            let (x, y) = (c as f64 / n as f64 - 0.5, r as f64 / n as f64 - 0.5);
            20.0 * (-(x * x + y * y) / 0.005).exp() + nd.sample(&mut rng)
        });
        let ax: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let img = Image::new(data, ax.clone(), ax);
        let s = pixel_noise(&img, true);
        // 9 900 differences: the MAD's relative error is about 1.1 %/… ≈ 1.5 %
        assert!((s / 0.3 - 1.0).abs() < 0.06, "σ = {s}");
    }
}
