//! `Image`: a 2-D array with physical axes, and `Profile`: a 1-D curve.
//!
//! Convention: `data[[row, col]]`; columns run along the horizontal axis (`x` values, µm),
//! rows along the vertical axis (`y` values, µm; `z` for XZ/YZ scans). Axis values are the
//! pixel centres, strictly monotonic.
//!
//! Statistics skip NaN pixels (unmeasured pixels of an aborted scan are NaN) and return an
//! error when no value is left; the standard deviation is the population one (`ddof = 0`,
//! like `numpy.nanstd`). Element-wise arithmetic checks shapes and keeps the left operand's
//! axes; scalar arithmetic refuses non-finite scalars (and division by zero) instead of
//! silently producing NaN or infinity.

use super::DataError;
use ndarray::{Array2, Axis};
use serde::{Deserialize, Serialize};
use std::fmt;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Pixel values, shape (rows, cols).
    pub data: Array2<f64>,
    /// Horizontal axis (one value per column), µm.
    pub x: Vec<f64>,
    /// Vertical axis (one value per row), µm.
    pub y: Vec<f64>,
    /// Names of the horizontal and vertical axes (`"x"`, `"y"`, `"z"`).
    pub x_name: String,
    pub y_name: String,
    /// Clipped and dark pixels, when the image came from a scan channel that has them
    /// ([`PixelFlags`], made by `data::clip`); carried through derivatives, arithmetic and crops so that
    /// analyses of the image flag them. Not saved with the image.
    #[serde(skip)]
    pub flags: Option<std::sync::Arc<PixelFlags>>,
}

/// The statistics methods of [`Image`] and [`Profile`] (each type's `stats(what)` over its
/// values; `what` names the operation in errors, e.g. "image mean").
macro_rules! summary_methods {
    // one field of `stats` per method, named after it ("image mean")
    (@field $noun:literal, $($field:ident: $doc:expr,)*) => {
        $(
            #[doc = $doc]
            pub fn $field(&self) -> Result<f64, DataError> {
                Ok(self.stats(concat!($noun, " ", stringify!($field)))?.$field)
            }
        )*
    };
    ($noun:literal, $value:literal) => {
        #[doc = concat!("min, max, mean, std and count of the non-NaN ", $value, "s in one pass.")]
        pub fn summary(&self) -> Result<Stats, DataError> {
            self.stats(concat!($noun, " summary"))
        }
        summary_methods!(@field $noun,
            min: concat!("Smallest ", $value, ", NaN skipped."),
            max: concat!("Largest ", $value, ", NaN skipped."),
            mean: concat!("Mean of the non-NaN ", $value, "s."),
            std: concat!("Population standard deviation (ddof = 0) of the non-NaN ", $value, "s."),
        );
        #[doc = concat!("Largest absolute ", $value, ", NaN skipped.")]
        pub fn abs_max(&self) -> Result<f64, DataError> {
            let s = self.stats(concat!($noun, " abs_max"))?;
            Ok(s.min.abs().max(s.max.abs()))
        }
    };
}

impl Image {
    /// Build an image; panics only on a programming error (axis lengths not matching the data),
    /// never on user input (callers validate first, or use [`Image::try_new`]).
    pub fn new(data: Array2<f64>, x: Vec<f64>, y: Vec<f64>) -> Self {
        assert_eq!(
            data.ncols(),
            x.len(),
            "x axis length must equal the number of columns"
        );
        assert_eq!(
            data.nrows(),
            y.len(),
            "y axis length must equal the number of rows"
        );
        Self {
            data,
            x,
            y,
            x_name: "x".into(),
            y_name: "y".into(),
            flags: None,
        }
    }

    /// Build an image from user input: axis lengths must match the data shape, axis values
    /// must be finite and strictly monotonic, and the image must not be empty.
    pub fn try_new(data: Array2<f64>, x: Vec<f64>, y: Vec<f64>) -> Result<Self, DataError> {
        if data.is_empty() {
            return Err(DataError::invalid(
                "data",
                format!("{}x{} array", data.nrows(), data.ncols()),
                "an image needs at least one row and one column",
            ));
        }
        if x.len() != data.ncols() {
            return Err(DataError::invalid(
                "x",
                format!("{} values", x.len()),
                &format!("the x axis needs one value per column ({})", data.ncols()),
            ));
        }
        if y.len() != data.nrows() {
            return Err(DataError::invalid(
                "y",
                format!("{} values", y.len()),
                &format!("the y axis needs one value per row ({})", data.nrows()),
            ));
        }
        check_axis("x", &x)?;
        check_axis("y", &y)?;
        Ok(Self::new(data, x, y))
    }

    pub fn with_axis_names(mut self, x_name: &str, y_name: &str) -> Self {
        self.x_name = x_name.into();
        self.y_name = y_name.into();
        self
    }

    pub fn rows(&self) -> usize {
        self.data.nrows()
    }
    pub fn cols(&self) -> usize {
        self.data.ncols()
    }
    /// `(rows, cols)`.
    pub fn shape(&self) -> (usize, usize) {
        (self.rows(), self.cols())
    }
    /// Pixel spacing along x (µm); 0 for a single column.
    pub fn dx(&self) -> f64 {
        axis_step(&self.x)
    }
    /// Pixel spacing along y (µm); 0 for a single row.
    pub fn dy(&self) -> f64 {
        axis_step(&self.y)
    }

    /// Number of NaN pixels (unmeasured pixels of an aborted scan).
    pub fn nan_count(&self) -> usize {
        self.data.iter().filter(|v| v.is_nan()).count()
    }

    fn stats(&self, what: &str) -> Result<Stats, DataError> {
        Stats::of(self.data.iter().copied(), what)
    }

    summary_methods!("image", "pixel");

    /// Row `i` as a profile along the horizontal axis (`t` = x values, named after `x_name`).
    pub fn row(&self, i: i64) -> Result<Profile, DataError> {
        let r = check_index("row", i, self.rows())?;
        Ok(Profile::along(&self.x, &self.x_name, self.data.row(r)))
    }

    /// Column `j` as a profile along the vertical axis (`t` = y values, named after `y_name`).
    pub fn col(&self, j: i64) -> Result<Profile, DataError> {
        let c = check_index("column", j, self.cols())?;
        Ok(Profile::along(&self.y, &self.y_name, self.data.column(c)))
    }

    /// The sub-image whose pixel centres lie within `x_range` and `y_range` (µm, inclusive,
    /// either order). A tolerance of 1e-9 pixel spacings absorbs rounding of the bounds.
    pub fn crop(&self, x_range: (f64, f64), y_range: (f64, f64)) -> Result<Image, DataError> {
        let cols = select_range(&self.x, x_range, &self.x_name)?;
        let rows = select_range(&self.y, y_range, &self.y_name)?;
        let data = self.data.select(Axis(0), &rows).select(Axis(1), &cols);
        let flags = self.flags.as_ref().and_then(|f| {
            let mask = f.mask.select(Axis(0), &rows).select(Axis(1), &cols);
            (mask.iter().any(|&m| m != 0) || f.unlocated != [0, 0]).then(|| {
                std::sync::Arc::new(PixelFlags {
                    mask,
                    ..(**f).clone()
                })
            })
        });
        Ok(Image {
            data,
            x: cols.iter().map(|&j| self.x[j]).collect(),
            y: rows.iter().map(|&i| self.y[i]).collect(),
            x_name: self.x_name.clone(),
            y_name: self.y_name.clone(),
            flags,
        })
    }

    fn zip_with(
        &self,
        other: &Image,
        op: &'static str,
        f: impl Fn(f64, f64) -> f64,
    ) -> Result<Image, DataError> {
        if self.shape() != other.shape() {
            return Err(DataError::ShapeMismatch {
                op,
                left: self.shape(),
                right: other.shape(),
            });
        }
        let mut out = self.clone();
        out.data.zip_mut_with(&other.data, |a, &b| *a = f(*a, b));
        Ok(out)
    }

    /// Element-wise sum; the shapes must agree. The result keeps `self`'s axes.
    pub fn add(&self, other: &Image) -> Result<Image, DataError> {
        self.zip_with(other, "image add", |a, b| a + b)
    }
    /// Element-wise difference `self - other`; the shapes must agree.
    pub fn sub(&self, other: &Image) -> Result<Image, DataError> {
        self.zip_with(other, "image sub", |a, b| a - b)
    }
    /// Element-wise product; the shapes must agree.
    pub fn mul(&self, other: &Image) -> Result<Image, DataError> {
        self.zip_with(other, "image mul", |a, b| a * b)
    }

    fn map_scalar(&self, k: f64, name: &str, f: impl Fn(f64) -> f64) -> Result<Image, DataError> {
        if !k.is_finite() {
            return Err(DataError::invalid(name, k, "must be a finite number"));
        }
        let mut out = self.clone();
        out.data.mapv_inplace(f);
        Ok(out)
    }

    /// Add a finite scalar to every pixel.
    pub fn add_scalar(&self, k: f64) -> Result<Image, DataError> {
        self.map_scalar(k, "scalar (add)", |v| v + k)
    }
    /// Subtract a finite scalar from every pixel.
    pub fn sub_scalar(&self, k: f64) -> Result<Image, DataError> {
        self.map_scalar(k, "scalar (sub)", |v| v - k)
    }
    /// Multiply every pixel by a finite scalar.
    pub fn mul_scalar(&self, k: f64) -> Result<Image, DataError> {
        self.map_scalar(k, "scalar (mul)", |v| v * k)
    }
    /// Divide every pixel by a finite, non-zero scalar.
    pub fn div_scalar(&self, k: f64) -> Result<Image, DataError> {
        if k == 0.0 {
            return Err(DataError::invalid(
                "scalar (div)",
                k,
                "division by zero; use a non-zero number",
            ));
        }
        self.map_scalar(k, "scalar (div)", |v| v / k)
    }
}

impl fmt::Display for Image {
    /// One line: shape, axis ranges in µm, value range and NaN count, e.g.
    /// `Image 64x64 (rows x cols), x -1..1 µm, y -1..1 µm, min -0.4289, max 0.4289`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Image {}x{} (rows x cols)", self.rows(), self.cols())?;
        write!(f, ", {} {}", self.x_name, axis_summary(&self.x))?;
        write!(f, ", {} {}", self.y_name, axis_summary(&self.y))?;
        match self.stats("") {
            Ok(s) => write!(f, ", min {}, max {}", fmt_sig(s.min, 4), fmt_sig(s.max, 4))?,
            Err(_) if self.data.is_empty() => write!(f, ", empty")?,
            Err(_) => write!(f, ", all NaN")?,
        }
        let nan = self.nan_count();
        if nan > 0 && nan < self.data.len() {
            write!(f, ", {nan} NaN")?;
        }
        Ok(())
    }
}

/// Mean spacing of a monotonic axis (0 if it has fewer than two points).
pub fn axis_step(a: &[f64]) -> f64 {
    if a.len() < 2 {
        0.0
    } else {
        (a[a.len() - 1] - a[0]) / (a.len() - 1) as f64
    }
}

/// Lengths of the segments of a polyline through `points` (in the vertices' unit, µm).
pub fn segment_lengths(points: &[[f64; 2]]) -> Vec<f64> {
    points
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .collect()
}

/// A 1-D curve: values `v` sampled at positions `t` (µm unless stated).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub t: Vec<f64>,
    pub v: Vec<f64>,
    /// What `t` measures (e.g. `"x"`, `"arc length"`).
    pub t_name: String,
}

impl Profile {
    /// The values `v` along the axis `t` named `t_name` (same length).
    fn along(t: &[f64], t_name: &str, v: ndarray::ArrayView1<f64>) -> Self {
        Self {
            t: t.to_vec(),
            v: v.to_vec(),
            t_name: t_name.into(),
        }
    }

    pub fn new(t: Vec<f64>, v: Vec<f64>) -> Self {
        assert_eq!(t.len(), v.len());
        Self {
            t,
            v,
            t_name: "x".into(),
        }
    }

    /// Build a profile from user input: `t` and `v` must have the same length.
    pub fn try_new(t: Vec<f64>, v: Vec<f64>) -> Result<Self, DataError> {
        if t.len() != v.len() {
            return Err(DataError::invalid(
                "v",
                format!("{} values", v.len()),
                &format!(
                    "a profile needs one value per position ({} positions)",
                    t.len()
                ),
            ));
        }
        Ok(Self::new(t, v))
    }

    pub fn with_t_name(mut self, name: &str) -> Self {
        self.t_name = name.into();
        self
    }

    pub fn len(&self) -> usize {
        self.v.len()
    }
    pub fn is_empty(&self) -> bool {
        self.v.is_empty()
    }

    fn stats(&self, what: &str) -> Result<Stats, DataError> {
        Stats::of(self.v.iter().copied(), what)
    }

    summary_methods!("profile", "value");
}

impl fmt::Display for Profile {
    /// One line: length, position range and value range.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "Profile {} points, {} {}",
            self.len(),
            self.t_name,
            axis_summary(&self.t)
        )?;
        match self.stats("") {
            Ok(s) => write!(f, ", min {}, max {}", fmt_sig(s.min, 4), fmt_sig(s.max, 4))?,
            Err(_) if self.v.is_empty() => write!(f, ", empty")?,
            Err(_) => write!(f, ", all NaN")?,
        }
        let nan = self.v.iter().filter(|v| v.is_nan()).count();
        if nan > 0 && nan < self.v.len() {
            write!(f, ", {nan} NaN")?;
        }
        Ok(())
    }
}

/// NaN-skipping summary statistics (from [`Image::summary`] / [`Profile::summary`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    pub min: f64,
    pub max: f64,
    pub mean: f64,
    pub std: f64,
    /// Number of non-NaN values.
    pub count: usize,
}

impl Stats {
    /// Statistics of the non-NaN values; error if there are none (empty or all NaN).
    pub fn of(values: impl Iterator<Item = f64>, what: &str) -> Result<Stats, DataError> {
        // Welford's update: one pass, numerically stable.
        let (mut n, mut mean, mut m2) = (0usize, 0.0f64, 0.0f64);
        let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
        let mut total = 0usize;
        for v in values {
            total += 1;
            if v.is_nan() {
                continue;
            }
            n += 1;
            min = min.min(v);
            max = max.max(v);
            let d = v - mean;
            mean += d / n as f64;
            m2 += d * (v - mean);
        }
        if total == 0 {
            return Err(DataError::Empty(what.to_string()));
        }
        if n == 0 {
            return Err(DataError::AllNaN {
                what: what.to_string(),
                count: total,
            });
        }
        Ok(Stats {
            min,
            max,
            mean,
            std: (m2 / n as f64).max(0.0).sqrt(),
            count: n,
        })
    }
}

fn check_index(what: &'static str, i: i64, len: usize) -> Result<usize, DataError> {
    if i < 0 || i as u64 >= len as u64 {
        Err(DataError::IndexOutOfRange {
            what,
            index: i,
            len,
        })
    } else {
        Ok(i as usize)
    }
}

fn check_axis(name: &str, a: &[f64]) -> Result<(), DataError> {
    if let Some((k, v)) = a.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(DataError::invalid(
            &format!("{name}[{k}]"),
            v,
            "axis values must be finite",
        ));
    }
    if a.len() >= 2 {
        let up = a[1] > a[0];
        for k in 1..a.len() {
            let ok = if up { a[k] > a[k - 1] } else { a[k] < a[k - 1] };
            if !ok {
                return Err(DataError::invalid(
                    &format!("{name}[{k}]"),
                    a[k],
                    &format!(
                        "axis values must be strictly monotonic (previous value {})",
                        a[k - 1]
                    ),
                ));
            }
        }
    }
    Ok(())
}

fn select_range(axis: &[f64], range: (f64, f64), name: &str) -> Result<Vec<usize>, DataError> {
    let arg = format!("{name}_range");
    if !range.0.is_finite() || !range.1.is_finite() {
        return Err(DataError::invalid(
            &arg,
            format!("[{}, {}]", range.0, range.1),
            "bounds must be finite numbers (µm)",
        ));
    }
    let (lo, hi) = if range.0 <= range.1 {
        range
    } else {
        (range.1, range.0)
    };
    let tol = 1e-9 * axis_step(axis).abs();
    let idx: Vec<usize> = (0..axis.len())
        .filter(|&k| axis[k] >= lo - tol && axis[k] <= hi + tol)
        .collect();
    if idx.is_empty() {
        return Err(DataError::invalid(
            &arg,
            format!("[{lo}, {hi}] µm"),
            &format!(
                "contains no pixel centre; the {name} axis spans {} µm",
                axis_summary_plain(axis)
            ),
        ));
    }
    Ok(idx)
}

fn axis_summary_plain(a: &[f64]) -> String {
    match a {
        [] => "nothing".into(),
        [v] => fmt_sig(*v, 5),
        _ => format!("{}..{}", fmt_sig(a[0], 5), fmt_sig(a[a.len() - 1], 5)),
    }
}

fn axis_summary(a: &[f64]) -> String {
    format!("{} µm", axis_summary_plain(a))
}

/// `v` with `sig` significant digits, trailing zeros removed; exponent form for very large or
/// very small magnitudes (like C's `%g`).
pub fn fmt_sig(v: f64, sig: usize) -> String {
    if !v.is_finite() {
        return super::format_f64_exact(v);
    }
    if v == 0.0 {
        return "0".into();
    }
    let sig = sig.max(1);
    let e = v.abs().log10().floor() as i32;
    if e < -4 || e >= sig as i32 {
        let s = format!("{:.*e}", sig - 1, v);
        // trim mantissa zeros: 1.500e-5 -> 1.5e-5
        if let Some((m, ex)) = s.split_once('e') {
            let m = if m.contains('.') {
                m.trim_end_matches('0').trim_end_matches('.')
            } else {
                m
            };
            return format!("{m}e{ex}");
        }
        s
    } else {
        let decimals = (sig as i32 - 1 - e).max(0) as usize;
        let s = format!("{:.*}", decimals, v);
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    }
}

/// Bit of [`PixelFlags::mask`]: the pixel is clipped (or computed from clipped pixels).
pub const CLIPPED: u8 = 1;
/// Bit of [`PixelFlags::mask`]: the pixel is dark (or computed from dark pixels).
pub const DARK: u8 = 2;

/// The clipped and dark pixels of an image taken from a scan channel (`scan.sx` at the
/// prompt), carried by the image through derivatives, arithmetic and crops, so that an
/// analysis of an image (`max_sens(sensitivity(scan.sx))`, `focus_search(scan.sx)`) sees them.
/// `data::clip` makes them from a scan and checks an analysis's pixels against them.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelFlags {
    /// Per pixel: [`CLIPPED`] and/or [`DARK`] bits.
    pub mask: Array2<u8>,
    /// The channel(s) whose samples were clipped (`"Sx"`; `"Sx, Sy"` after arithmetic).
    pub channel: String,
    /// What the image is when its pixels are computed from the channel's (`"the derivative"`),
    /// `None` for the channel itself.
    pub derived: Option<String>,
    /// `"±0.2 V input range"`, when the scan says.
    pub range: Option<String>,
    /// `"0.02 V on the sum input"`, when the scan says.
    pub floor: Option<String>,
    /// Clipped and dark pixels known only from the metadata (a file without the per-pixel
    /// arrays): reported whatever the pixels used.
    pub unlocated: [usize; 2],
}

impl PixelFlags {
    /// The flags of an image computed from this one by a stencil reaching `rx` columns and `ry`
    /// rows either side (a derivative): a pixel is flagged when any pixel it uses is.
    pub fn derived(&self, what: &str, rx: usize, ry: usize) -> PixelFlags {
        let (rows, cols) = self.mask.dim();
        let mut mask = Array2::<u8>::zeros((rows, cols));
        for ((r, c), &m) in self.mask.indexed_iter() {
            if m == 0 {
                continue;
            }
            for rr in r.saturating_sub(ry)..(r + ry + 1).min(rows) {
                for cc in c.saturating_sub(rx)..(c + rx + 1).min(cols) {
                    mask[[rr, cc]] |= m;
                }
            }
        }
        PixelFlags {
            mask,
            derived: Some(what.to_string()),
            ..self.clone()
        }
    }

    /// The flags of a pixel-wise combination of two images of the same shape.
    pub fn union(&self, other: &PixelFlags) -> PixelFlags {
        let mut out = self.clone();
        if out.mask.dim() == other.mask.dim() {
            out.mask.zip_mut_with(&other.mask, |a, &b| *a |= b);
        }
        if !out.channel.split(", ").any(|c| c == other.channel) {
            out.channel = format!("{}, {}", out.channel, other.channel);
        }
        out.derived = out.derived.or_else(|| other.derived.clone());
        out.range = out.range.or_else(|| other.range.clone());
        out.floor = out.floor.or_else(|| other.floor.clone());
        for (a, b) in out.unlocated.iter_mut().zip(other.unlocated) {
            *a = (*a).max(b);
        }
        out
    }

    /// The flags of rows `r0..=r1` and columns `c0..=c1`; `None` when none is left there.
    pub fn crop(&self, (r0, r1): (usize, usize), (c0, c1): (usize, usize)) -> Option<PixelFlags> {
        let mask = self.mask.slice(ndarray::s![r0..=r1, c0..=c1]).to_owned();
        (mask.iter().any(|&m| m != 0) || self.unlocated != [0, 0]).then(|| PixelFlags {
            mask,
            ..self.clone()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fmt_sig_examples() {
        assert_eq!(fmt_sig(0.428923, 4), "0.4289");
        assert_eq!(fmt_sig(-1.0, 4), "-1");
        assert_eq!(fmt_sig(1.5e-5, 4), "1.5e-5");
        assert_eq!(fmt_sig(123456.0, 4), "1.235e5");
        assert_eq!(fmt_sig(12.5, 4), "12.5");
    }
}
