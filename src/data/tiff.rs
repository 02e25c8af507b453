//! Float32 TIFF export for Fiji/ImageJ, and a reader for round trips.
//!
//! One page, one sample per pixel, `BitsPerSample = 32`, `SampleFormat = IEEEFP`, no
//! compression, rows in array order (row 0 = first axis value = top of the image in Fiji).
//! The pixel size goes where ImageJ looks for it: `XResolution`/`YResolution` = pixels per µm
//! and an `ImageDescription` starting with `ImageJ=` that says `unit=micron`, the display range
//! (`min=`, `max=`, NaN pixels excluded) and the origin (`xorigin=`, `yorigin=`, in pixels) so
//! that Fiji's cursor read-out shows the scan's µm coordinates. Extra `bfpscope_*` lines (which
//! ImageJ ignores) keep the exact axis start, step and names for [`load_tiff`].

use super::image::fmt_sig;
use super::{atomic_write, DataError, Image};
use ::tiff::decoder::{ifd::Value, Decoder, DecodingResult, Limits};
use ::tiff::encoder::{colortype::Gray32Float, Rational, TiffEncoder};
use ::tiff::tags::{ResolutionUnit, Tag};
use ndarray::Array2;
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::Path;

/// Save `img` as a single-page float32 grayscale TIFF (atomically). Values are rounded to
/// the nearest `f32`; NaN stays NaN.
pub fn save_tiff(path: impl AsRef<Path>, img: &Image) -> Result<(), DataError> {
    let path = path.as_ref();
    let (rows, cols) = img.shape();
    if rows == 0 || cols == 0 {
        return Err(DataError::Empty(format!("save_tiff {}", path.display())));
    }
    let (w, h) = match (u32::try_from(cols), u32::try_from(rows)) {
        (Ok(w), Ok(h)) => (w, h),
        _ => {
            return Err(DataError::invalid(
                "image size",
                format!("{rows}x{cols}"),
                "at most 2^32-1 pixels per side",
            ))
        }
    };
    let pixels: Vec<f32> = img.data.iter().map(|&v| v as f32).collect();
    let description = imagej_description(img);
    let (px, py) = (
        pixel_size(img.dx(), img.dy()),
        pixel_size(img.dy(), img.dx()),
    );
    atomic_write(path, |tmp| {
        let terr = |e: ::tiff::TiffError| DataError::format(path, format!("writing TIFF: {e}"));
        let file = File::create(tmp).map_err(|e| DataError::io(tmp, e))?;
        let mut enc = TiffEncoder::new(BufWriter::new(file)).map_err(terr)?;
        let mut image = enc.new_image::<Gray32Float>(w, h).map_err(terr)?;
        let dir = image.encoder();
        dir.write_tag(Tag::ImageDescription, description.as_str())
            .map_err(terr)?;
        dir.write_tag(Tag::Software, "bfpscope").map_err(terr)?;
        // ImageJ: with unit=micron in the description, XResolution is pixels per micron and
        // ResolutionUnit stays "none".
        dir.write_tag(Tag::ResolutionUnit, ResolutionUnit::None.to_u16())
            .map_err(terr)?;
        dir.write_tag(Tag::XResolution, per_unit_rational(px))
            .map_err(terr)?;
        dir.write_tag(Tag::YResolution, per_unit_rational(py))
            .map_err(terr)?;
        image.write_data(&pixels).map_err(terr)
    })
}

/// Pixel size for the TIFF header: |step|, or the other axis's step for a single-pixel axis,
/// or 1 µm when both are single pixels.
fn pixel_size(step: f64, other: f64) -> f64 {
    let s = step.abs();
    if s > 0.0 && s.is_finite() {
        s
    } else if other.abs() > 0.0 && other.is_finite() {
        other.abs()
    } else {
        1.0
    }
}

/// `1/size` as a TIFF rational n/d with d = 10^k as large as fits.
fn per_unit_rational(size: f64) -> Rational {
    let per = 1.0 / size;
    for k in (0..=9).rev() {
        let d = 10f64.powi(k);
        let n = (per * d).round();
        if n >= 1.0 && n <= f64::from(u32::MAX) {
            return Rational {
                n: n as u32,
                d: d as u32,
            };
        }
    }
    // Extremely large pixels (>= 1e9 µm / px): the smallest representable density.
    Rational { n: 1, d: u32::MAX }
}

fn imagej_description(img: &Image) -> String {
    let (dx, dy) = (img.dx(), img.dy());
    let (px, py) = (pixel_size(dx, dy), pixel_size(dy, dx));
    let mut s = String::from("ImageJ=1.54f\nunit=micron\n");
    if let (Ok(lo), Ok(hi)) = (img.min(), img.max()) {
        if lo.is_finite() && hi.is_finite() {
            s += &format!("min={}\nmax={}\n", lo as f32, hi as f32);
        }
    }
    // ImageJ calibration: value = (pixel - origin) * pixel size.
    let x0 = img.x.first().copied().unwrap_or(0.0);
    let y0 = img.y.first().copied().unwrap_or(0.0);
    // 12 significant digits hide rounding noise (3 rather than 2.999999999999999)
    if x0 != 0.0 && dx >= 0.0 {
        s += &format!("xorigin={}\n", fmt_sig(-x0 / px, 12));
    }
    if y0 != 0.0 && dy >= 0.0 {
        s += &format!("yorigin={}\n", fmt_sig(-y0 / py, 12));
    }
    s += &format!(
        "bfpscope_x0={}\nbfpscope_dx={}\nbfpscope_y0={}\nbfpscope_dy={}\nbfpscope_xname={}\nbfpscope_yname={}\n",
        x0,
        dx,
        y0,
        dy,
        one_line(&img.x_name),
        one_line(&img.y_name)
    );
    s
}

fn one_line(s: &str) -> String {
    s.replace(['\n', '\r', '='], "_")
}

/// Read a single-page grayscale TIFF (float32 as written by [`save_tiff`]; float64 and 8/16/32-bit
/// integer images are converted). Axes come from the `bfpscope_*` description lines when present,
/// else from ImageJ's calibration (`unit=micron`, `XResolution`, `xorigin`), else pixel indices.
pub fn load_tiff(path: impl AsRef<Path>) -> Result<Image, DataError> {
    let path = path.as_ref();
    let terr = |e: ::tiff::TiffError| DataError::format(path, format!("reading TIFF: {e}"));
    let file = File::open(path).map_err(|e| DataError::io(path, e))?;
    let mut dec = Decoder::new(BufReader::new(file))
        .map_err(terr)?
        .with_limits(Limits::unlimited());
    let (w, h) = dec.dimensions().map_err(terr)?;
    let (cols, rows) = (w as usize, h as usize);
    let values: Vec<f64> = match dec.read_image().map_err(terr)? {
        DecodingResult::F32(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::F64(v) => v,
        DecodingResult::U8(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::U16(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::U32(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::I16(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::I32(v) => v.into_iter().map(f64::from).collect(),
        _ => {
            return Err(DataError::format(
                path,
                "unsupported sample type (expected float32)",
            ))
        }
    };
    if values.len() != rows * cols {
        return Err(DataError::format(
            path,
            format!(
                "{} samples for a {w}x{h} image: only single-channel (grayscale) images are supported",
                values.len()
            ),
        ));
    }
    let data = Array2::from_shape_vec((rows, cols), values)
        .map_err(|e| DataError::format(path, e.to_string()))?;

    let desc = match dec.find_tag(Tag::ImageDescription) {
        Ok(Some(Value::Ascii(s))) => s,
        _ => String::new(),
    };
    let props: HashMap<&str, &str> = desc
        .lines()
        .filter_map(|l| l.split_once('='))
        .map(|(k, v)| (k.trim(), v.trim_end_matches('\0').trim()))
        .collect();
    let num = |k: &str| props.get(k).and_then(|v| v.parse::<f64>().ok());
    let rational = |dec: &mut Decoder<BufReader<File>>, tag| match dec.find_tag(tag) {
        Ok(Some(Value::Rational(n, d))) if n > 0 && d > 0 => Some(f64::from(d) / f64::from(n)),
        _ => None,
    };
    let (x, y) = if let (Some(x0), Some(dx), Some(y0), Some(dy)) = (
        num("bfpscope_x0"),
        num("bfpscope_dx"),
        num("bfpscope_y0"),
        num("bfpscope_dy"),
    ) {
        (uniform_axis(x0, dx, cols), uniform_axis(y0, dy, rows))
    } else if matches!(
        props.get("unit"),
        Some(&"micron") | Some(&"um") | Some(&"µm")
    ) {
        let pw = rational(&mut dec, Tag::XResolution).unwrap_or(1.0);
        let ph = rational(&mut dec, Tag::YResolution).unwrap_or(pw);
        let (ox, oy) = (num("xorigin").unwrap_or(0.0), num("yorigin").unwrap_or(0.0));
        (
            uniform_axis(-ox * pw, pw, cols),
            uniform_axis(-oy * ph, ph, rows),
        )
    } else {
        (uniform_axis(0.0, 1.0, cols), uniform_axis(0.0, 1.0, rows))
    };
    let xname = props.get("bfpscope_xname").copied().unwrap_or("x");
    let yname = props.get("bfpscope_yname").copied().unwrap_or("y");
    Ok(Image::new(data, x, y).with_axis_names(xname, yname))
}

fn uniform_axis(start: f64, step: f64, n: usize) -> Vec<f64> {
    (0..n).map(|k| start + step * k as f64).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rationals() {
        let r = per_unit_rational(0.02);
        assert!((f64::from(r.d) / f64::from(r.n) - 0.02).abs() < 1e-12);
        let r = per_unit_rational(250.0);
        assert!((f64::from(r.d) / f64::from(r.n) - 250.0).abs() < 1e-6);
        let r = per_unit_rational(1e-4);
        assert!((f64::from(r.d) / f64::from(r.n) - 1e-4).abs() < 1e-15);
    }

    #[test]
    fn description_is_imagej() {
        let img = Image::new(
            Array2::from_shape_fn((2, 3), |(i, j)| (i * 3 + j) as f64),
            vec![-0.5, 0.0, 0.5],
            vec![1.0, 1.25],
        );
        let d = imagej_description(&img);
        assert!(d.starts_with("ImageJ="), "{d}");
        assert!(d.contains("\nunit=micron\n"));
        assert!(d.contains("\nmin=0\nmax=5\n"));
        assert!(d.contains("\nxorigin=1\n"), "{d}");
        assert!(d.contains("\nyorigin=-4\n"), "{d}");
    }
}
