//! [`MeasureOptions`]: the measurement pipeline for maximum sensitivities (derivative stencil,
//! parabola window over 0.4 µm as in Sec. 5, detection thresholds), shared by the bead model,
//! the orientation calibration and the quantities' calibrations. A leaf, re-exported by
//! `orientation`.

use super::check_range;
use super::peaks::PeakOptions;
use super::sensitivity::Stencil;
use super::Result;
use serde::{Deserialize, Serialize};

/// The measurement pipeline for maximum sensitivities: derivative stencil, parabola window,
/// and detection threshold (per-line SNR; 0 = off).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MeasureOptions {
    pub stencil: Stencil,
    /// Parabola window, µm (paper: 0.4).
    pub window_um: f64,
    /// Per-line maxima below min_snr × line noise are ignored (0: keep all).
    pub min_snr: f64,
    /// Maxima farther than this from the fitted filament line are ignored, µm.
    pub max_offset_um: f64,
    /// Candidate maxima for the line search must exceed detect_snr × the pixel noise of the
    /// sensitivity image (1.4826·MAD of first differences/√2).
    pub detect_snr: f64,
    /// Maxima closer than this to an end of the filament inside the scan are left out of the
    /// mean, µm: the end lowers them (to 50 % at the end; in the paper's beam 3 % at 0.3 µm,
    /// 1.6 % at 0.6 µm, ≤ 0.5 % from 0.8 µm on, by the simulator's bead model).
    pub end_margin_um: f64,
}

impl Default for MeasureOptions {
    fn default() -> Self {
        Self {
            stencil: Stencil::Central2,
            window_um: 0.4,
            min_snr: 0.0,
            max_offset_um: 0.15,
            detect_snr: 4.0,
            end_margin_um: 0.8,
        }
    }
}

impl MeasureOptions {
    pub(crate) fn validate(&self) -> Result<()> {
        check_range("window_um", self.window_um, 1e-3, 100.0)?;
        check_range("min_snr", self.min_snr, 0.0, 1e6)?;
        check_range("max_offset_um", self.max_offset_um, 0.0, 100.0)?;
        check_range("detect_snr", self.detect_snr, 0.0, 1e6)?;
        check_range("end_margin_um", self.end_margin_um, 0.0, 100.0)?;
        Ok(())
    }
    pub(crate) fn peak_options(&self) -> PeakOptions {
        PeakOptions {
            window_um: self.window_um,
            min_snr: self.min_snr,
            ..Default::default()
        }
    }
}
