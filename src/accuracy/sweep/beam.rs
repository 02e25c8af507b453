//! The beam family of the truth sweep (`fit_beam.*`): an XY scan (±1.2 µm) of one
//! polystyrene reference bead in a vector beam of random pupil filling, seen by a QPD of random
//! misalignment, fitted by `fit_beam` with its domain checks as the binding runs it
//! ([`crate::analysis::checked::fit_beam_scan`]); or an empty field.
//!
//! Truth, by a path apart from the analysis: the scene's own parameters, which the simulator
//! renders (`optics::mie_beam`, the `misalignment` effect) and the fit does not see: v = 1/f0²
//! of the beam, the QPD's rotation δ, the squares of its offsets (cone radii²: at the focus an
//! offset enters at second order and its sign is not measured) and Sy gain ratio, the bead's
//! position; the beam is x-polarised (ψ = 0).

use super::field::{
    bead_words, clip_words, draw_clip, empty_field_outcome, one_bead_scene, render_field,
};
use super::focus::Outcome;
use crate::analysis::beam_fit::{BeamFit, BeamFitOptions};
use crate::analysis::checked::fit_beam_scan;
use crate::optics::params::{Beam, Optics, REF_BEAD_N};
use crate::optics::rayleigh::Misalignment;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

/// Half the side of the scenes' field, µm (the fit needs 1.2 µm around the bead).
const HALF_UM: f64 = 1.2;

/// The scenes' pixel sizes, nm (the fit takes pixels up to 100 nm).
const PIXELS_NM: [u32; 5] = [20, 30, 50, 75, 100];

/// One beam-fit scene: the bead `[x µm, y µm, z µm, d nm]` (z: its height above the focal
/// plane; None: an empty field), the beam's v = 1/f0² (0: uniformly filled pupil), the QPD's
/// misalignment `[offset_x, offset_y, rotation_deg, gain_y]` (None: aligned), the paper's noise
/// × `noise`, pixels of `pixel_nm`, the noise's `seed`, the digitiser's range.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct BeamCase {
    pub bead: Option<[f64; 4]>,
    pub inv_f0_sq: f64,
    pub misalignment: Option<[f64; 4]>,
    pub noise: f64,
    pub pixel_nm: u32,
    pub seed: u64,
    #[serde(default)]
    pub clip: Option<f64>,
}

impl BeamCase {
    /// One field in eight empty; otherwise a 60–180 nm bead (log-uniform; the fit is told its
    /// size, as a user names the reference bead) within ±0.55 µm of the centre (the fit's
    /// domain: 0.6 µm inside the edge) for three scenes in four and ±1.3 µm (at and beyond the
    /// edge) for the others; in the focal plane for half the scenes, within ±0.1 µm of it for
    /// a quarter (a scan "at the focus" is as good as the focus search before it) and ±1 µm
    /// for the others; v = 1/f0² of 0 (a uniformly filled pupil) for one
    /// scene in four, else 0.1–2 (f0 0.7–3.2); the QPD aligned for one scene in four, else
    /// offsets of ±0.15 cone radii, a rotation of ±5° and an Sy gain of 0.6–1.2; noise × 0–10;
    /// one scene in four clipped.
    pub(super) fn draw(rng: &mut ChaCha8Rng) -> BeamCase {
        let empty = rng.random_range(0..8) == 0;
        let reach = if rng.random_range(0..4) == 0 {
            1.3
        } else {
            0.55
        };
        let x = rng.random_range(-reach..reach);
        let y = rng.random_range(-reach..reach);
        let z = match rng.random_range(0..4) {
            0 | 1 => 0.0,
            2 => rng.random_range(-0.1..0.1),
            _ => rng.random_range(-1.0..1.0),
        };
        let d = (60f64.ln() + rng.random::<f64>() * 3f64.ln()).exp();
        let inv_f0_sq = if rng.random_range(0..4) == 0 {
            0.0
        } else {
            rng.random_range(0.1..2.0)
        };
        let misalignment = (rng.random_range(0..4) != 0).then(|| {
            [
                rng.random_range(-0.15..0.15),
                rng.random_range(-0.15..0.15),
                rng.random_range(-5.0..5.0),
                rng.random_range(0.6..1.2),
            ]
        });
        let noise = rng.random_range(0.0..10.0);
        let pixel_nm = PIXELS_NM[rng.random_range(0..PIXELS_NM.len())];
        let seed = rng.random::<u64>();
        BeamCase {
            bead: (!empty).then_some([x, y, z, d]),
            inv_f0_sq,
            misalignment,
            noise,
            pixel_nm,
            seed,
            clip: draw_clip(rng),
        }
    }

    pub(super) fn describe(&self) -> String {
        format!(
            "beam: {}, v = 1/f0² {:.4}, QPD {}, noise ×{:.4}, pixel {} nm on ±{HALF_UM} µm, seed {}{}",
            bead_words(self.bead),
            self.inv_f0_sq,
            match self.misalignment {
                Some([ox, oy, r, g]) => format!(
                    "offsets ({ox:.4}, {oy:.4}), rotation {r:.3}°, gain_y {g:.4}"
                ),
                None => "aligned".into(),
            },
            self.noise,
            self.pixel_nm,
            self.seed,
            clip_words(self.clip)
        )
    }

    /// The scene's optics: the sweep's, in the vector beam of the drawn pupil filling.
    fn optics(&self, base: &Optics) -> Optics {
        Optics {
            beam: Beam::Vector,
            pupil_filling: if self.inv_f0_sq > 0.0 {
                1.0 / self.inv_f0_sq.sqrt()
            } else {
                f64::INFINITY
            },
            ..base.clone()
        }
    }

    fn mis(&self) -> Misalignment {
        let [offset_x, offset_y, rotation_deg, gain_y] =
            self.misalignment.unwrap_or([0.0, 0.0, 0.0, 1.0]);
        Misalignment {
            offset_x,
            offset_y,
            rotation_deg,
            gain_y,
        }
    }
}

/// The estimators of the family, in the order [`beam_case`] reports them.
pub const KEYS: [&str; 9] = [
    "fit_beam.inv_f0_sq",
    "fit_beam.qpd_rotation_deg",
    "fit_beam.polarization_deg",
    "fit_beam.gain_ratio",
    "fit_beam.offset_x_sq",
    "fit_beam.offset_y_sq",
    "fit_beam.defocus_sq",
    "fit_beam.x0",
    "fit_beam.y0",
];

/// The key of the empty fields' estimator.
pub const DETECTION: &str = "fit_beam.detection";

/// The fit and its warnings, for `--replay`.
pub(super) type BeamAnswer = (BeamFit, Vec<String>);

/// The beam family: one scene fitted; each parameter against the scene's, an empty field
/// against "no bead". Returns each estimator's outcome and the fit with its warnings (for
/// `--replay`).
pub(super) fn beam_case(
    case: &BeamCase,
    base: &Optics,
) -> (Vec<(&'static str, Outcome)>, Option<BeamAnswer>) {
    let optics = case.optics(base);
    let mut sc = one_bead_scene(case.bead);
    sc.effects.misalignment = case.misalignment.map(|_| case.mis());
    let keys: &[&'static str] = if case.bead.is_some() {
        &KEYS
    } else {
        &[DETECTION]
    };
    let all = |o: Outcome| keys.iter().map(|k| (*k, o.clone())).collect::<Vec<_>>();
    let Some(scan) = render_field(
        &optics,
        sc,
        HALF_UM,
        case.pixel_nm as f64 / 1000.0,
        (case.noise, case.clip),
        case.seed,
    ) else {
        return (all(Outcome::Refused), None);
    };
    let opts = BeamFitOptions {
        d_nm: case.bead.map_or(110.0, |b| b[3].clamp(40.0, 200.0)),
        n: REF_BEAD_N,
        ..BeamFitOptions::default()
    };
    // the session's optics as a user has them before the fit: the beam is what is fitted
    let session = Optics {
        beam: Beam::Paraxial,
        ..base.clone()
    };
    let r = fit_beam_scan(&session, &scan, &opts);
    let why: Vec<String> = match &r {
        Ok((_, w)) => w.clone(),
        Err(e) => vec![e.clone()],
    };
    let Some(bead) = case.bead else {
        let found = r.as_ref().ok().map(|(f, _)| (f.x0.value, f.y0.value));
        let o = empty_field_outcome(found, why, &case.describe());
        return (vec![(DETECTION, o)], r.ok());
    };
    let f = match &r {
        Ok((f, _)) if why.is_empty() => f,
        _ => return (all(Outcome::Flagged(why)), r.ok()),
    };
    let m = case.mis();
    let truths = [
        (f.inv_f0_sq, case.inv_f0_sq),
        (f.qpd_rotation_deg, m.rotation_deg),
        (f.polarization_deg, 0.0),
        (f.gain_ratio, m.gain_y),
        (f.offset_x_sq, m.offset_x * m.offset_x),
        (f.offset_y_sq, m.offset_y * m.offset_y),
        (f.defocus_sq, bead[2] * bead[2]),
        (f.x0, bead[0]),
        (f.y0, bead[1]),
    ];
    let out: Vec<(&'static str, Outcome)> = KEYS
        .iter()
        .zip(truths)
        .map(|(k, (v, t))| {
            (
                *k,
                Outcome::Answer {
                    value: v.value,
                    truth: t,
                    sigma: Some(v.sigma),
                    rel_limit: None,
                    what: format!(
                        "{} {:.5} ± {:.5} vs truth {t:.5}: {}",
                        &k["fit_beam.".len()..],
                        v.value,
                        v.sigma,
                        case.describe()
                    ),
                },
            )
        })
        .collect();
    (out, r.ok())
}
