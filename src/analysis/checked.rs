//! The filament analyses and the beam fit of a whole scan with the checks of their inputs (`data::clip`: the
//! clipped and dark pixels among those they read), as the bindings, the protocols and the truth
//! sweep run them: one function each, so that a Rust caller gets the same warnings and refusals
//! as a script.
//!
//! Errors are plain sentences that name the step that refused (`"measure_filament: …"`,
//! `"remove_background: …"`), as the bindings say them.

use super::background::{remove_point_background, BackgroundOptions, Remaining};
use super::beam_fit::{fit_beam, BeamFit, BeamFitOptions, DEFOCUS_DCHI2, DEFOCUS_LIN_UM, V_MAX};
use super::fit::FitResult;
use super::orientation::{measure_filament, AngleCurve, Channel, FilamentMeasurement};
use super::template::Template;
use super::MeasureOptions;
use crate::data::clip::InputCheck;
use crate::data::{Scan, ScanStatus};
use crate::optics::params::Optics;

/// `measure_filament` on a scan (Sec. 4.2 steps 4–5), with the clipped and dark pixels among
/// those it reads added to its warnings (every one of them bad: a refusal).
pub fn measure_filament_scan(
    scan: &Scan,
    curve: &AngleCurve,
    mo: &MeasureOptions,
) -> Result<FilamentMeasurement, String> {
    let who = "measure_filament";
    let mut r =
        measure_filament(&scan.sx, &scan.sy, curve, mo).map_err(|e| format!("{who}: {e}"))?;
    let check = filament_input_check(scan, &r, mo);
    r.warnings.extend(check.gate(who)?);
    Ok(r)
}

/// The clipped and dark pixels (`data::clip`) among those a filament measurement reads: in the
/// channel it used, the parabola window around each line's maximum, widened by the stencil.
pub fn filament_input_check(
    scan: &Scan,
    r: &FilamentMeasurement,
    mo: &MeasureOptions,
) -> InputCheck {
    let reach = mo.stencil.reach() as f64;
    let img = &scan.sx;
    let step = |v: &[f64]| {
        if v.len() > 1 {
            (v[v.len() - 1] - v[0]).abs() / (v.len() - 1) as f64
        } else {
            0.0
        }
    };
    let rows = r.channel == Channel::SxRows;
    let (ch, half) = if rows {
        ("sx", 0.5 * mo.window_um + reach * step(&img.x))
    } else {
        ("sy", 0.5 * mo.window_um + reach * step(&img.y))
    };
    let mut centre = vec![None; if rows { img.y.len() } else { img.x.len() }];
    for p in &r.points {
        if let Some(v) = centre.get_mut(p.line) {
            *v = Some(if rows { p.x } else { p.y });
        }
    }
    let half = half * (1.0 + 1e-9);
    crate::data::clip::input_check_where(scan, &[ch], |row, col| {
        let (line, at) = if rows {
            (row, img.x[col])
        } else {
            (col, img.y[row])
        };
        centre[line].is_some_and(|c| (at - c).abs() <= half)
    })
}

/// What [`remove_background_scan`] returns.
#[derive(Debug, Clone)]
pub struct Cleaned {
    /// The scan with the point objects subtracted; its metadata says so
    /// (`background_removed: {axis, n_objects, objects: [[x µm, y µm, weight]…], footprint}`,
    /// the footprint where each object's subtraction can move a filament's maxima,
    /// [`super::background::Footprint`]), its clipped pixels stay flagged.
    pub scan: Scan,
    /// The fit of the point objects (None when nothing was detected).
    pub fit: Option<FitResult>,
    /// Point-like features still there at ≥ `REMAINING_SNR` × the detection map's noise.
    pub remaining: Vec<Remaining>,
    /// The sentence saying so, None when there is none.
    pub warning: Option<String>,
    /// The clipped or dark pixels of Sx and Sy, then `warning`.
    pub warnings: Vec<String>,
    /// The faintest point object the removal detects, reference-bead units
    /// ([`super::background::BackgroundResult::detection_limit`]).
    pub detection_limit: Option<f64>,
}

impl Cleaned {
    /// The point objects removed (the fit's beads; 0 when nothing was detected).
    pub fn n_objects(&self) -> usize {
        n_fitted(&self.fit)
    }
}

fn n_fitted(fit: &Option<FitResult>) -> usize {
    fit.as_ref().map_or(0, |f| f.beads.len())
}

/// `remove_background` on a scan (Sec. 6, Fig. 6): the point objects fitted in one channel and
/// subtracted from both; both channels' clipped and dark pixels checked (every one bad: a
/// refusal), the features left after the removal said in words.
pub fn remove_background_scan(
    scan: &Scan,
    tpl: &Template,
    bo: &BackgroundOptions,
) -> Result<Cleaned, String> {
    let who = "remove_background";
    // both channels are read: the objects are fitted in one and subtracted from the other
    let mut warnings = crate::data::clip::input_check(scan, &["sx", "sy"], None).gate(who)?;
    let r =
        remove_point_background(&scan.sx, &scan.sy, tpl, bo).map_err(|e| format!("{who}: {e}"))?;
    let n_objects = n_fitted(&r.fit);
    let mut meta = scan.meta.clone();
    let objects: Vec<[f64; 3]> = r.fit.as_ref().map_or(vec![], |f| {
        f.beads.iter().map(|b| [b.x, b.y, b.weight]).collect()
    });
    let footprint = (!objects.is_empty()).then(|| super::background::Footprint::of(tpl, bo.axis));
    meta["background_removed"] = serde_json::json!({
        "axis": format!("{:?}", bo.axis),
        "n_objects": n_objects,
        "objects": objects,
        "footprint": footprint,
        "detection_limit": r.detection_limit,
    });
    let cleaned = Scan {
        sx: r.sx,
        sy: r.sy,
        sz: scan.sz.clone(),
        status: ScanStatus::Complete,
        meta,
        raw: Vec::new(),
        flags: scan.flags.clone(),
    };
    let warning = remaining_warning(&r.remaining);
    warnings.extend(warning.clone());
    Ok(Cleaned {
        scan: cleaned,
        fit: r.fit,
        remaining: r.remaining,
        warning,
        warnings,
        detection_limit: r.detection_limit,
    })
}

/// The warning for point-like features left after a removal (`None` when there are none).
pub fn remaining_warning(rem: &[Remaining]) -> Option<String> {
    use super::background::REMAINING_SNR;
    if rem.is_empty() {
        return None;
    }
    let list: Vec<String> = rem
        .iter()
        .take(5)
        .map(|f| {
            let snr = f
                .snr
                .map_or("noise-free data".to_string(), |s| format!("SNR {s:.1}"));
            format!(
                "({:.3}, {:.3}) µm, {:.3} reference beads, {snr}",
                f.x, f.y, f.weight
            )
        })
        .collect();
    Some(format!(
        "{} point-like feature{} still in the scan after the removal (at ≥ {REMAINING_SNR} × the detection map's noise): {}{}; lower detect_snr or min_weight to remove {}",
        rem.len(),
        if rem.len() == 1 { "" } else { "s" },
        list.join("; "),
        if rem.len() > 5 { "; …" } else { "" },
        if rem.len() == 1 { "it" } else { "them" }
    ))
}

/// Half the field the beam fit needs around the bead, µm (`analysis::beam_fit`: ≥ 1.2 µm).
pub const BEAM_FIT_FIELD_HALF_UM: f64 = 0.6;

/// `fit_beam` on a scan, inside its domain (docs/analysis.md, Domains): no clipped or dark
/// pixel among the three channels it fits (every one: a refusal), the bead whole inside the
/// 1.2 µm field it needs, v = 1/f0² not at the search's upper bound. Returns the fit and its
/// warnings.
pub fn fit_beam_scan(
    optics: &Optics,
    scan: &Scan,
    opts: &BeamFitOptions,
) -> Result<(BeamFit, Vec<String>), String> {
    let who = "fit_beam";
    let check = crate::data::clip::input_check(scan, &["sx", "sy", "sz"], None);
    let mut warnings = check.gate(who)?;
    let f =
        fit_beam(optics, &scan.sx, &scan.sy, &scan.sz, opts).map_err(|e| format!("{who}: {e}"))?;
    warnings.extend(super::domain::margin_warning(
        "the bead",
        &scan.sx,
        f.x0.value,
        f.y0.value,
        BEAM_FIT_FIELD_HALF_UM,
    ));
    if f.defocus.dchi2 > DEFOCUS_DCHI2 {
        warnings.push(format!(
            "the bead is not at the height the model puts it ({} µm): the scan fits better {:.2} µm from the focus (Δχ² = {:.1} > {DEFOCUS_DCHI2}), and a bead off the focus reads as a smaller pupil filling and a QPD offset; focus on the bead first (focus_search)",
            opts.z_um, f.defocus.z_um.abs(), f.defocus.dchi2
        ));
    } else if f.defocus_sq.value > DEFOCUS_LIN_UM * DEFOCUS_LIN_UM {
        warnings.push(format!(
            "the bead is about {:.2} µm off the focus (its fitted height² {:.3} ± {:.3} µm²): the model follows a height to ±{DEFOCUS_LIN_UM} µm, and further off it reads a smaller pupil filling and QPD offsets; focus on the bead first (focus_search)",
            f.defocus_sq.value.sqrt(), f.defocus_sq.value, f.defocus_sq.sigma
        ));
    }
    if f.inv_f0_sq.value >= V_MAX * (1.0 - 1e-9) {
        warnings.push(format!(
            "the pupil filling is at the search's bound v = 1/f0² = {V_MAX} (a beam much narrower than the pupil): its value and σ do not hold; check the bead's size and index and the optics"
        ));
    }
    Ok((f, warnings))
}
