//! Point objects on a filament below the aggregate removal's detection limit (Sec. 6): a matched
//! filter along the filament's line, in the channel the filament barely shows in.
//!
//! `remove_background`'s CLEAN finds objects in a smoothed derivative map of the fitted channel,
//! over the whole field, down to `detect_snr` (6) × that map's robust noise. The derivative map
//! weighs each pixel by the template's derivative over a few pixels, not by its response: a 34 nm
//! aggregate at 2× the paper's noise on 20 nm pixels passes under it, yet adds to every maximum of
//! the filament within the template's reach and moves μ by 4–5 σ(μ) (docs/accuracy.md,
//! thirteenth session). Here the least-squares weight of one point object is read at each point
//! of a band along the filament's line, from the fitted channel's pixels within
//! [`FAINT_HALF_UM`] of it: W = Σ R·D / Σ R², R the template's response in that channel (instrument
//! units per reference bead), D the cleaned channel, σ(W) = σ_pix / √Σ R² (the matched filter:
//! the detection with the highest SNR for a known shape in white noise). The filament's own
//! uniform residue in that channel is the same all along its line and is taken out as the median
//! of W along it. σ_pix is the larger of the noise along the rows and along the columns
//! ([`pixel_noise`]); noise correlated over the window (a drift within it) is outside the
//! filter's domain. Objects at [`MIN_FAINT_SNR`] or more are
//! reported; `microtubule::density` turns each into the rise of μ it causes.

use super::template::Template;
use super::AxisMap;
use crate::data::Image;
use serde::{Deserialize, Serialize};

/// Half the side of the square of pixels each weight is read from, µm. The reference bead's
/// response at the paper's optics (the truth sweep's template) holds 96 % of its Σ R² in Sy
/// within it and 85 % in Sx (97 and 98 % within 0.5 µm): the window gives up a few % of the
/// SNR for less of the neighbouring structure (other objects, a removal's residual).
pub const FAINT_HALF_UM: f64 = 0.4;

/// Smallest W/σ(W) reported. Along the line W's main lobe is ~0.34 µm wide (full width at
/// half maximum, for the closed-form stand-in of `w` = 0.25 µm), and the band's lateral offsets
/// are 0.1 µm apart, so a line of ~5 µm (the sweep's 4 µm field) holds some 40 independent
/// places: noise alone passes 5σ (one-sided: 2.9·10⁻⁷) at one of them in ~1 scene in 10⁵.
pub const MIN_FAINT_SNR: f64 = 5.0;

/// Lateral offsets of the band from the line, µm (aggregates of Sec. 6 sit on the filament or
/// beside it; the sweep's scenes put half of them within 0.4 µm of its line).
const LATERAL_UM: [f64; 5] = [-0.2, -0.1, 0.0, 0.1, 0.2];

/// Two reports closer than this are one object (the stronger kept), µm: more than the band's
/// lateral step × 4, so that one structure read at both −0.2 and +0.2 µm is one.
const SEPARATION_UM: f64 = 0.45;

/// Places within this distance of a removed object are not searched (its subtraction's residual
/// is not a new object, and the maxima it moves are left out of μ by its footprint), µm.
const REMOVED_CLEAR_UM: f64 = 0.3;

/// A point object found by the matched filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Faint {
    /// Position, µm.
    pub x: f64,
    pub y: f64,
    /// Weight (reference-bead units) above the line's median, and its 1σ.
    pub weight: f64,
    pub weight_err: f64,
    /// weight / weight_err.
    pub snr: f64,
}

/// The matched filter's weight of one object at (x0, y0) in channel `ch` (0 Sx, 1 Sy) and its
/// Σ R² (instrument units² per reference bead²). `None` where the window leaves the image or
/// holds a non-finite pixel.
fn weight_at(img: &Image, ch: usize, tpl: &Template, x0: f64, y0: f64) -> Option<(f64, f64)> {
    let (ax, ay) = (AxisMap::new(&img.x), AxisMap::new(&img.y));
    // the same number of pixels about the nearest one wherever the object lies: Σ R² and the
    // filament's residue in W then do not change with the window's phase on the pixels
    let span = |m: &AxisMap, at: f64| -> Option<std::ops::Range<usize>> {
        let k = (FAINT_HALF_UM / m.h.abs().max(1e-12)).round() as usize;
        let c = m.nearest(at)?;
        (c >= k && c + k < m.n).then(|| c - k..c + k + 1)
    };
    let (cols, rows) = (span(&ax, x0)?, span(&ay, y0)?);
    let (mut rd, mut rr) = (0.0, 0.0);
    for r in rows {
        let v = img.y[r] - y0;
        for c in cols.clone() {
            let d = img.data[[r, c]];
            if !d.is_finite() {
                return None;
            }
            let s = tpl.eval(img.x[c] - x0, v)[ch] / tpl.norm_factor;
            rd += s * d;
            rr += s * s;
        }
    }
    (rr > 0.0).then(|| (rd / rr, rr))
}

/// The pixel noise of `img`: the robust spread of its second differences, /√6 (a slowly varying
/// signal cancels in them), along its rows and along its columns, the larger. A drift between
/// lines (noise that is not white across them) raises the second; the matched filter's σ then
/// errs on the safe side. On noise-free data, [`NOISE_FLOOR_REL`] of the largest |value|.
pub fn pixel_noise(img: &Image) -> f64 {
    let along = |lanes: ndarray::iter::Lanes<'_, f64, ndarray::Ix1>| {
        let d: Vec<f64> = lanes
            .into_iter()
            .flat_map(|l| {
                l.windows(3)
                    .into_iter()
                    .map(|w| w[0] - 2.0 * w[1] + w[2])
                    .collect::<Vec<_>>()
            })
            .collect();
        super::stats::robust_std(&d).map_or(0.0, |s| s / 6f64.sqrt())
    };
    let floor = NOISE_FLOOR_REL * img.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    along(img.data.rows())
        .max(along(img.data.columns()))
        .max(floor)
}

/// The pixel noise is never taken below this fraction of the image's largest |value|: on
/// noise-free images the template's interpolation and the rounding leave their own scatter,
/// which is not an object. Where the noise is that low, the floor only makes σ(W) larger.
const NOISE_FLOOR_REL: f64 = 1e-4;

/// Point objects at [`MIN_FAINT_SNR`] or more in channel `ch` (0 Sx, 1 Sy) of the cleaned
/// image `img`, on the band along `line` (the filament's axis points, in order along it; `normal`
/// its unit normal), away from the `removed` objects (x, y µm). Strongest first. Empty on a line
/// too short to take a median along.
pub fn search(
    img: &Image,
    ch: usize,
    tpl: &Template,
    line: &[[f64; 2]],
    normal: [f64; 2],
    removed: &[[f64; 2]],
) -> Vec<Faint> {
    let sigma_pix = pixel_noise(img);
    if !(sigma_pix > 0.0) || line.len() < 5 {
        // (0 only on an image that is 0 everywhere)
        return vec![];
    }
    let clear = |x: f64, y: f64| {
        removed
            .iter()
            .all(|o| (o[0] - x).hypot(o[1] - y) > REMOVED_CLEAR_UM)
    };
    let mut found: Vec<Faint> = vec![];
    for l in LATERAL_UM {
        // (x, y, W, Σ R²) along the line at this offset
        let at: Vec<(f64, f64, f64, f64)> = line
            .iter()
            .filter_map(|p| {
                let (x, y) = (p[0] + l * normal[0], p[1] + l * normal[1]);
                weight_at(img, ch, tpl, x, y).map(|(w, rr)| (x, y, w, rr))
            })
            .collect();
        let ws: Vec<f64> = at.iter().map(|a| a.2).collect();
        let Some(med) = super::stats::median(&ws) else {
            continue;
        };
        if at.len() < 5 {
            continue;
        }
        for &(x, y, w, rr) in &at {
            let err = sigma_pix / rr.sqrt();
            let (weight, snr) = (w - med, (w - med) / err);
            if snr >= MIN_FAINT_SNR && clear(x, y) {
                found.push(Faint {
                    x,
                    y,
                    weight,
                    weight_err: err,
                    snr,
                });
            }
        }
    }
    found.sort_by(|a, b| b.snr.total_cmp(&a.snr));
    let mut kept: Vec<Faint> = vec![];
    for f in found {
        if kept
            .iter()
            .all(|k| (k.x - f.x).hypot(k.y - f.y) > SEPARATION_UM)
        {
            kept.push(f);
        }
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// A 5 µm field of 20 nm pixels holding, in Sy, `objects` (x, y µm, weight) of the
    /// closed-form stand-in (Sy = v·exp(−(u² + v²)/w²), w = 0.25 µm), a uniform ridge along the
    /// y axis (a filament's residue in the fitted channel) and white noise of `sigma`.
    fn field(tpl: &Template, objects: &[(f64, f64, f64)], sigma: f64, seed: u64) -> Image {
        let axis: Vec<f64> = (0..251).map(|i| -2.5 + 0.02 * i as f64).collect();
        let [_, sy, _] = tpl.render_instrument(objects, &axis, &axis);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut img = Image::new(sy, axis.clone(), axis.clone());
        for ((_, c), v) in img.data.indexed_iter_mut() {
            let x = axis[c];
            let z: f64 = StandardNormal.sample(&mut rng);
            *v += 0.01 * x * (-x * x / 0.0625).exp() + sigma * z;
        }
        img
    }

    fn line() -> Vec<[f64; 2]> {
        (0..=200).map(|i| [0.0, -2.0 + 0.02 * i as f64]).collect()
    }

    fn tpl() -> Template {
        Template::analytic_standin(0.25, 0.01, 1.0).unwrap()
    }

    /// Σ R² of the stand-in's Sy on 20 nm pixels: ∫ v²·e^(−2r²/w²) dA / h² = π w⁴ / (8 h²).
    fn sum_r2() -> f64 {
        std::f64::consts::PI * 0.25f64.powi(4) / (8.0 * 0.02 * 0.02)
    }

    #[test]
    fn the_matched_filters_weight_is_unbiased_and_its_sigma_is_the_closed_form() {
        let t = tpl();
        let sigma = 0.004;
        let n = 120;
        let z: Vec<f64> = (0..n)
            .map(|s| {
                let img = field(&t, &[(0.0, 0.2, 0.02)], sigma, s);
                let (w, rr) = weight_at(&img, 1, &t, 0.0, 0.2).unwrap();
                // Σ R² over the window: the closed form less the ~1 % of the lobes beyond it
                assert!((rr / sum_r2() - 1.0).abs() < 0.02, "{rr} vs {}", sum_r2());
                (w - 0.02) / (sigma / rr.sqrt())
            })
            .collect();
        let s = crate::analysis::stats::summary(&z).unwrap();
        // mean 0 ± 1/√120 (3σ: 0.27), sd 1 ± 1/√240 (3σ: 0.19)
        assert!(s.mean.abs() < 0.27, "mean z {}", s.mean);
        assert!((s.std - 1.0).abs() < 0.19, "sd z {}", s.std);
        // and the pixel noise is read back from the image
        let img = field(&t, &[], sigma, 1);
        assert!((pixel_noise(&img) / sigma - 1.0).abs() < 0.05);
    }

    #[test]
    fn a_faint_object_on_the_line_is_found_at_its_weight_and_place() {
        let t = tpl();
        let sigma = 0.004;
        let err = sigma / sum_r2().sqrt();
        for seed in 0..5 {
            // 10σ, 0.03 µm beside the line
            let img = field(&t, &[(0.03, 0.4, 10.0 * err)], sigma, 100 + seed);
            let f = search(&img, 1, &t, &line(), [1.0, 0.0], &[]);
            assert_eq!(f.len(), 1, "{f:?}");
            let o = f[0];
            // on the band's grid: along the line every 20 nm, across it every 0.1 µm
            assert!(
                (o.y - 0.4).abs() <= 0.04 && (o.x - 0.03).abs() <= 0.1,
                "{o:?}"
            );
            assert!((o.weight / err - 10.0).abs() < 4.0, "{o:?}");
            assert!((o.weight_err / err - 1.0).abs() < 0.15, "{o:?}");
            // beside a removed object it is not searched
            assert!(search(&img, 1, &t, &line(), [1.0, 0.0], &[[0.0, 0.5]]).is_empty());
        }
    }

    #[test]
    fn noise_and_the_filaments_own_residue_are_not_objects() {
        let t = tpl();
        for seed in 0..40 {
            let f = search(
                &field(&t, &[], 0.004, 200 + seed),
                1,
                &t,
                &line(),
                [1.0, 0.0],
                &[],
            );
            assert!(f.is_empty(), "seed {seed}: {f:?}");
        }
        // noise-free, an object of 0.1 % of the reference bead stands out of the signal's own
        // curvature, at its weight
        let f = search(
            &field(&t, &[(0.0, 0.4, 0.001)], 0.0, 0),
            1,
            &t,
            &line(),
            [1.0, 0.0],
            &[],
        );
        assert_eq!(f.len(), 1, "{f:?}");
        assert!((f[0].weight / 0.001 - 1.0).abs() < 0.05, "{f:?}");
    }
}
