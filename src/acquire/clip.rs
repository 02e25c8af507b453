//! Clipped and dark pixels of a scan, counted while it runs: every acquisition mode reports the
//! samples its digitiser took at or beyond the input's rail, per pixel and per channel
//! (`Strategy::take_clipped`, with [`line_counts`] for rasters); at the end
//! [`ClipTally::finish`] adds the dark pixels (the sum
//! below the QPD's floor), stores the counts in the scan (`Scan::flags`), summarises them in
//! `meta.clipped` and `meta.dark`, and tells the operator.

pub use crate::data::clip::{ClipTally, ClippedPixel};
use crate::instrument::range::{CLIP_SX, CLIP_SY, CLIP_SZ};

/// The clipped samples per pixel of a line binned as `raster::bin_line` bins it: `flags`
/// (one per sample, [`crate::instrument::range::clip_bits`]; shorter than `positions` means
/// the rest are 0) counted into the pixel of each sample's measured position; samples outside
/// the line count nowhere.
pub fn line_counts(positions: &[f64], flags: &[u8], from: f64, to: f64, n: usize) -> Vec<[u32; 3]> {
    let mut out = vec![[0u32; 3]; n];
    if n < 2 || from == to {
        return out;
    }
    let w = (to - from) / (n - 1) as f64;
    for (&x, &f) in positions.iter().zip(flags) {
        if f == 0 || !x.is_finite() {
            continue;
        }
        // the pixel bin_line puts the sample in
        let u = (x - from) / w + 0.5;
        if u >= 0.0 && u < n as f64 {
            let i = u as usize;
            for (k, bit) in [CLIP_SX, CLIP_SY, CLIP_SZ].into_iter().enumerate() {
                out[i][k] += u32::from(f & bit != 0);
            }
        }
    }
    out
}

/// The pixels of one raster line (`row`) with a clipped sample.
pub fn line_pixels(row: usize, counts: &[[u32; 3]]) -> Vec<ClippedPixel> {
    counts
        .iter()
        .enumerate()
        .filter(|(_, c)| c.iter().any(|&k| k > 0))
        .map(|(col, c)| (row, col, *c))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clipped_samples_land_in_the_pixel_bin_line_uses() {
        // 3 pixels at 0, 0.5, 1 µm: pixel edges at 0.25 and 0.75
        let x = [-0.3, 0.1, 0.24, 0.26, 0.8, 1.3];
        let f = [
            CLIP_SX,
            CLIP_SX,
            CLIP_SY,
            CLIP_SX | CLIP_SZ,
            CLIP_SZ,
            CLIP_SX,
        ];
        let c = line_counts(&x, &f, 0.0, 1.0, 3);
        assert_eq!(c, vec![[1, 1, 0], [1, 0, 1], [0, 0, 1]]);
        // shorter flags: the rest count 0
        assert_eq!(
            line_counts(&x, &f[..2], 0.0, 1.0, 3),
            vec![[1, 0, 0], [0; 3], [0; 3]]
        );
        assert_eq!(line_pixels(4, &c)[1], (4, 1, [1, 0, 1]));
    }
}
