//! Colour maps: a blue–white–red diverging map (ColorBrewer RdBu, reversed) for signed signals
//! such as Sx and Sy, and viridis for one-signed quantities such as Sz or sensitivities.

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

const VIRIDIS: [(u8, u8, u8); 9] = [
    (0x44, 0x01, 0x54),
    (0x47, 0x2d, 0x7b),
    (0x3b, 0x52, 0x8b),
    (0x2c, 0x72, 0x8e),
    (0x21, 0x91, 0x8c),
    (0x28, 0xae, 0x80),
    (0x5e, 0xc9, 0x62),
    (0xad, 0xdc, 0x30),
    (0xfd, 0xe7, 0x25),
];

impl Colormap {
    /// Colour at fraction `t` of the range (clamped to [0, 1]); NaN gives [`NAN_RGB`].
    pub fn rgb(self, t: f64) -> (u8, u8, u8) {
        if t.is_nan() {
            return NAN_RGB;
        }
        let table: &[(u8, u8, u8)] = match self {
            Colormap::Diverging => &RDBU_R,
            Colormap::Sequential => &VIRIDIS,
        };
        interpolate(table, t.clamp(0.0, 1.0))
    }

    /// Colour of value `v` on the scale `[vmin, vmax]`.
    pub fn rgb_value(self, v: f64, vmin: f64, vmax: f64) -> (u8, u8, u8) {
        if v.is_nan() {
            return NAN_RGB;
        }
        self.rgb((v - vmin) / (vmax - vmin))
    }
}

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
        assert_eq!(c.rgb_value(0.0, -2.0, 2.0), (0xf7, 0xf7, 0xf7));
        let (r, _, b) = c.rgb_value(-1.5, -2.0, 2.0);
        assert!(b > r + 50, "negative values are blue");
        let (r, _, b) = c.rgb_value(1.5, -2.0, 2.0);
        assert!(r > b + 50, "positive values are red");
        assert_eq!(c.rgb(f64::NAN), NAN_RGB);
        // clamped outside the range
        assert_eq!(c.rgb(7.0), RDBU_R[10]);
    }

    #[test]
    fn viridis_ends() {
        assert_eq!(Colormap::Sequential.rgb(0.0), VIRIDIS[0]);
        assert_eq!(Colormap::Sequential.rgb(1.0), VIRIDIS[8]);
    }
}
