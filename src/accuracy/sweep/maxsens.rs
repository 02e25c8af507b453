//! The max_sens family of the truth sweep (`max_sens.value`, `max_sens.detection`): an XY
//! scan (±1.2 µm) of one polystyrene bead, in the focal plane or up to ±3 µm from it, or of an
//! empty field; its sensitivity ∂Sx/∂x (central differences) read by `max_sens` (Sec. 5: row
//! parabolas over 0.4 µm, refined across rows) as the binding reads it.
//!
//! Truth, by a path apart from the analysis: the noise-free renderer's largest ∂Sx/∂x near the
//! bead at the scene's focus offset, the maximum of a 2-D search (rows every 20 nm over ±0.3 µm
//! of the bead, central differences every 1 nm along each; refined across rows by the parabola
//! through the best row and its neighbours). What `max_sens` estimates is the pipeline's
//! reading of that peak (pixel size, stencil, window: 1 % low at 30 nm pixels, 7 % at 100 nm
//! in the focal plane, less for a defocused, wider peak), so the truth is the peak times the
//! reading of a peak of 1 at the scene's pixel size and focus offset: the reference template
//! built at that offset, read by [`Template::pipeline_max_sens`](crate::analysis::template::Template::pipeline_max_sens) (averaged over sub-pixel
//! positions), tabulated every [`Z_NODE_UM`] and interpolated.

use super::field::{
    bead_words, clip_words, draw_clip, empty_field_outcome, one_bead_scene, render_field,
};
use super::focus::Outcome;
use crate::analysis::peaks::PeakOptions;
use crate::analysis::sensitivity::{sensitivity, Axis, Stencil};
use crate::instrument::sim::scene::{Bead, Scene};
use crate::instrument::sim::Renderer;
use crate::optics::params::{Optics, REF_BEAD_N};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::collections::BTreeMap;
use std::sync::Mutex;

/// Half the side of the scenes' field, µm.
const HALF_UM: f64 = 1.2;

/// The scenes' pixel sizes, nm.
const PIXELS_NM: [u32; 6] = [10, 20, 30, 50, 75, 100];

/// The spacing of the focus offsets at which the pipeline's reading is tabulated, µm.
const Z_NODE_UM: f64 = 0.1;

/// One max_sens scene: the bead `[x µm, y µm, z µm, d nm]` (z: its height above the focal
/// plane; None: an empty field), the paper's noise × `noise`, pixels of `pixel_nm`, the noise's
/// `seed`, the digitiser's range (None: none).
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct MaxSensCase {
    pub bead: Option<[f64; 4]>,
    pub noise: f64,
    pub pixel_nm: u32,
    pub seed: u64,
    #[serde(default)]
    pub clip: Option<f64>,
}

impl MaxSensCase {
    /// One field in eight empty; otherwise a 40–200 nm bead (log-uniform) anywhere within
    /// ±1.1 µm (some near the edge), in the focal plane for half the scenes and up to ±3 µm
    /// from it for the others; noise × 0–10; one scene in four clipped.
    pub(super) fn draw(rng: &mut ChaCha8Rng) -> MaxSensCase {
        let empty = rng.random_range(0..8) == 0;
        let x = rng.random_range(-1.1..1.1);
        let y = rng.random_range(-1.1..1.1);
        let z = if rng.random_range(0..2) == 0 {
            0.0
        } else {
            rng.random_range(-3.0..3.0)
        };
        let d = (40f64.ln() + rng.random::<f64>() * (200f64 / 40.0).ln()).exp();
        let noise = rng.random_range(0.0..10.0);
        let pixel_nm = PIXELS_NM[rng.random_range(0..PIXELS_NM.len())];
        let seed = rng.random::<u64>();
        MaxSensCase {
            bead: (!empty).then_some([x, y, z, d]),
            noise,
            pixel_nm,
            seed,
            clip: draw_clip(rng),
        }
    }

    pub(super) fn describe(&self) -> String {
        format!(
            "max_sens: {}, noise ×{:.4}, pixel {} nm on ±{HALF_UM} µm, seed {}{}",
            bead_words(self.bead),
            self.noise,
            self.pixel_nm,
            self.seed,
            clip_words(self.clip)
        )
    }

    /// The tabulation nodes (index of z / [`Z_NODE_UM`]) the truth interpolates between.
    pub(super) fn z_nodes(&self) -> Option<[i32; 2]> {
        let z = self.bead?[2] / Z_NODE_UM;
        Some([z.floor() as i32, z.ceil() as i32])
    }
}

/// The pipeline's reading of a peak of 1, by (pixel nm, focus offset node): [`reading`].
#[derive(Default)]
pub(super) struct Readings(Mutex<BTreeMap<(u32, i32), Option<f64>>>);

impl Readings {
    pub(super) fn get(&self, optics: &Optics, pixel_nm: u32, node: i32) -> Option<f64> {
        if let Some(v) = self
            .0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(&(pixel_nm, node))
        {
            return *v;
        }
        let v = reading(optics, pixel_nm, node as f64 * Z_NODE_UM);
        self.0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert((pixel_nm, node), v);
        v
    }

    /// The reading at the scene's offset, interpolated linearly between its nodes.
    fn at(&self, optics: &Optics, case: &MaxSensCase) -> Option<f64> {
        let [a, b] = case.z_nodes()?;
        let ra = self.get(optics, case.pixel_nm, a)?;
        if a == b {
            return Some(ra);
        }
        let rb = self.get(optics, case.pixel_nm, b)?;
        let f = case.bead?[2] / Z_NODE_UM - a as f64;
        Some(ra + f * (rb - ra))
    }
}

/// The pipeline's reading of a peak of 1 at pixels of `pixel_nm`, `z` µm from the focus: the
/// reference bead rendered noise-free on the scenes' field at 4 × 4 sub-pixel offsets, read by
/// `max_sens`, the mean over its [`true_peak`]. (The reference template built at that offset,
/// `Template::from_optics(…, z)`, read 0.27–0.48 of what the pipeline reads beyond 2.4 µm from
/// the focus: its normalisation does not hold there.)
fn reading(optics: &Optics, pixel_nm: u32, z: f64) -> Option<f64> {
    let bead = [0.0, 0.0, z, REF_D_NM];
    let peak = true_peak(optics, bead)?;
    let r = lone_bead(optics, z, REF_D_NM)?;
    let h = pixel_nm as f64 / 1000.0;
    let n = (2.0 * HALF_UM / h).round() as usize + 1;
    let (mut acc, mut cnt) = (0.0, 0);
    for oy in 0..4 {
        for ox in 0..4 {
            let axis = |o: usize| -> Vec<f64> {
                (0..n)
                    .map(|i| -HALF_UM + i as f64 * h + o as f64 * h / 4.0)
                    .collect()
            };
            let (xs, ys) = (axis(ox), axis(oy));
            let s = r.render_grid_ideal(&xs, &ys, 0.0);
            let data = ndarray::Array2::from_shape_vec((n, n), s[0].clone()).ok()?;
            let img = crate::data::Image::new(data, xs, ys);
            let sens = sensitivity(&img, Axis::X, Stencil::Central2).ok()?;
            if let Ok(p) = crate::analysis::peaks::point_peak(&sens, &PeakOptions::default()) {
                acc += p.value;
                cnt += 1;
            }
        }
    }
    (cnt > 0).then(|| acc / cnt as f64 / peak)
}

/// The reference bead's diameter, nm.
const REF_D_NM: f64 = 110.0;

/// The renderer of a scene holding one polystyrene bead of `d_nm`, `z` µm above the focal
/// plane at the origin, nothing else.
fn lone_bead(optics: &Optics, z: f64, d_nm: f64) -> Option<Renderer> {
    let mut sc = Scene::default();
    sc.add_bead(Bead {
        pos: [0.0, 0.0, z],
        d_nm,
        n: REF_BEAD_N,
    })
    .ok()?;
    Renderer::checked(optics, &sc, Default::default()).ok()
}

/// The largest ∂Sx/∂x of the bead `[x, y, z, d]` alone, noise-free (µm⁻¹): see the module
/// docs. None where no maximum is found within ±0.3 µm along the rows, ±1 µm across them.
pub(super) fn true_peak(optics: &Optics, bead: [f64; 4]) -> Option<f64> {
    let [_, _, z, d] = bead;
    let r = lone_bead(optics, z, d)?;
    let h = 1e-3;
    let xs: Vec<f64> = (0..=600).map(|i| -0.3 + h * i as f64).collect();
    // (beyond ~1.1 µm from the focus the largest slope lies on side lobes 0.45–0.55 µm
    // across the rows from the bead)
    let ys: Vec<f64> = (0..=100).map(|i| -1.0 + 0.02 * i as f64).collect();
    let s = r.render_grid_ideal(&xs, &ys, 0.0);
    let nx = xs.len();
    // each row's largest slope, refined by the parabola through its neighbours
    let row_max: Vec<f64> = (0..ys.len())
        .map(|j| {
            let row = &s[0][j * nx..(j + 1) * nx];
            let d: Vec<f64> = (1..nx - 1)
                .map(|i| (row[i + 1] - row[i - 1]) / (2.0 * h))
                .collect();
            parabola_max(&d).unwrap_or(f64::NAN)
        })
        .collect();
    parabola_max(&row_max)
}

/// The largest interior sample of `v`, refined by the parabola through it and its neighbours
/// (None when it is at an end, or the three are not finite and concave).
fn parabola_max(v: &[f64]) -> Option<f64> {
    // (a NaN, a row without an interior maximum, is no maximum)
    let key = |i: usize| {
        if v[i].is_finite() {
            v[i]
        } else {
            f64::NEG_INFINITY
        }
    };
    let i = (1..v.len().checked_sub(1)?).max_by(|&a, &b| key(a).total_cmp(&key(b)))?;
    let (a, b, c) = (v[i - 1], v[i], v[i + 1]);
    let den = a - 2.0 * b + c;
    if den >= 0.0 || !(a + b + c).is_finite() {
        return None;
    }
    Some(b - (a - c) * (a - c) / (8.0 * den))
}

/// `max_sens`'s answer on a scene: the maximum and its warnings.
pub(super) type MaxSensAnswer = (crate::analysis::peaks::Peak2, Vec<String>);

/// The max_sens family: one XY scene, its ∂Sx/∂x read by `max_sens`; the value against the
/// truth, an empty field against "no object". Returns each estimator's outcome and the answer
/// (for `--replay`).
pub(super) fn maxsens_case(
    case: &MaxSensCase,
    optics: &Optics,
    readings: &Readings,
) -> (Vec<(&'static str, Outcome)>, Option<MaxSensAnswer>) {
    let keys = ["max_sens.value", "max_sens.detection"];
    let sc = one_bead_scene(case.bead);
    let key = if case.bead.is_some() {
        keys[0]
    } else {
        keys[1]
    };
    let Some(scan) = render_field(
        optics,
        sc,
        HALF_UM,
        case.pixel_nm as f64 / 1000.0,
        (case.noise, case.clip),
        case.seed,
    ) else {
        return (vec![(key, Outcome::Refused)], None);
    };
    // Sx with its clipped and dark pixels, as `scan.sx` gives it to a script
    let mut sx = scan.sx.clone();
    sx.flags = crate::data::clip::PixelFlags::of_channel(&scan, "sx").map(std::sync::Arc::new);
    let r = sensitivity(&sx, Axis::X, Stencil::Central2)
        .and_then(|s| crate::analysis::peaks::max_sens(&s, &PeakOptions::default()));
    let why: Vec<String> = match &r {
        Ok((_, w)) => w.clone(),
        Err(e) => vec![e.to_string()],
    };
    let Some(bead) = case.bead else {
        let found = r.as_ref().ok().map(|(p, _)| (p.x, p.y));
        let o = empty_field_outcome(found, why, &case.describe());
        return (vec![(key, o)], r.ok());
    };
    let p = match &r {
        Ok((p, _)) if why.is_empty() => *p,
        _ => return (vec![(key, Outcome::Flagged(why))], r.ok()),
    };
    let (Some(peak), Some(read)) = (true_peak(optics, bead), readings.at(optics, case)) else {
        return (vec![(key, Outcome::Refused)], r.ok());
    };
    let truth = peak * read;
    let what = format!(
        "max_sens {:.5} ± {:.5} µm⁻¹ vs truth {truth:.5}: {}",
        p.value,
        p.value_err.unwrap_or(f64::NAN),
        case.describe()
    );
    let o = Outcome::Answer {
        value: p.value,
        truth,
        sigma: p.value_err,
        rel_limit: None,
        what,
    };
    (vec![(key, o)], r.ok())
}
