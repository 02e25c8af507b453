//! Colour maps: ColorBrewer RdBu, reversed (blue–white–red), for signed signals such as Sx and
//! Sy, and viridis for one-signed quantities such as Sz or sensitivities.
//!
//! - Viridis is the `colorous` crate's (matplotlib's 256 published samples).
//! - RdBu is matplotlib's definition: linear interpolation between ColorBrewer's 11 RdBu classes
//!   (matplotlib `_cm.py`, `_RdBu_data`). colorous' RED_BLUE is d3's B-spline through the same
//!   classes, which misses the white centre (#f1efed instead of #f7f7f7), so the 11 published
//!   classes are kept here.

/// Which colour map a heat map uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Colormap {
    /// Blue (negative) – white (centre) – red (positive); use with a symmetric range.
    Diverging,
    /// Viridis: dark blue (low) to yellow (high), perceptually uniform.
    Sequential,
}

/// Colour of pixels without data (NaN).
pub const NAN_RGB: (u8, u8, u8) = (150, 150, 150);

/// ColorBrewer RdBu (11 classes), reversed: blue … #f7f7f7 … red.
const RDBU_R: [(u8, u8, u8); 11] = [
    (0x05, 0x30, 0x61),
    (0x21, 0x66, 0xac),
    (0x43, 0x93, 0xc3),
    (0x92, 0xc5, 0xde),
    (0xd1, 0xe5, 0xf0),
    (0xf7, 0xf7, 0xf7),
    (0xfd, 0xdb, 0xc7),
    (0xf4, 0xa5, 0x82),
    (0xd6, 0x60, 0x4d),
    (0xb2, 0x18, 0x2b),
    (0x67, 0x00, 0x1f),
];

impl Colormap {
    /// Colour at fraction `t` of the range (clamped to [0, 1]); NaN gives [`NAN_RGB`].
    pub fn rgb(self, t: f64) -> (u8, u8, u8) {
        if t.is_nan() {
            return NAN_RGB;
        }
        let t = t.clamp(0.0, 1.0);
        match self {
            Colormap::Diverging => interpolate(&RDBU_R, t),
            Colormap::Sequential => {
                let c = colorous::VIRIDIS.eval_continuous(t);
                (c.r, c.g, c.b)
            }
        }
    }

    /// Colour of value `v` on the scale `[vmin, vmax]`.
    pub fn rgb_value(self, v: f64, vmin: f64, vmax: f64) -> (u8, u8, u8) {
        if v.is_nan() {
            return NAN_RGB;
        }
        self.rgb((v - vmin) / (vmax - vmin))
    }
}

/// Linear interpolation in a table of equally spaced colours, `t` in [0, 1].
fn interpolate(table: &[(u8, u8, u8)], t: f64) -> (u8, u8, u8) {
    let x = t * (table.len() - 1) as f64;
    let k = (x.floor() as usize).min(table.len() - 2);
    let f = x - k as f64;
    let (a, b) = (table[k], table[k + 1]);
    let mix = |p: u8, q: u8| (f64::from(p) + f * (f64::from(q) - f64::from(p))).round() as u8;
    (mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn diverging_is_white_at_centre_blue_below_red_above() {
        let c = Colormap::Diverging;
        // ColorBrewer RdBu's centre class is #f7f7f7
        assert_eq!(c.rgb_value(0.0, -2.0, 2.0), (0xf7, 0xf7, 0xf7));
        let (r, _, b) = c.rgb_value(-1.5, -2.0, 2.0);
        assert!(b > r + 50, "negative values are blue");
        let (r, _, b) = c.rgb_value(1.5, -2.0, 2.0);
        assert!(r > b + 50, "positive values are red");
        assert_eq!(c.rgb(f64::NAN), NAN_RGB);
        // ends: RdBu's darkest classes #053061 (blue) and #67001f (red); clamped outside
        assert_eq!(c.rgb(-3.0), (0x05, 0x30, 0x61));
        assert_eq!(c.rgb(7.0), (0x67, 0x00, 0x1f));
    }

    #[test]
    fn viridis_published_values() {
        // matplotlib's viridis: #440154 at 0, #21918c at 0.5, #fde725 at 1
        assert_eq!(Colormap::Sequential.rgb(0.0), (0x44, 0x01, 0x54));
        assert_eq!(Colormap::Sequential.rgb(1.0), (0xfd, 0xe7, 0x25));
        let (r, g, b) = Colormap::Sequential.rgb(0.5);
        assert!(
            r.abs_diff(0x21) <= 1 && g.abs_diff(0x91) <= 1 && b.abs_diff(0x8c) <= 1,
            "{:?}",
            (r, g, b)
        );
    }
}
