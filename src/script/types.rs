//! Rhai types `Scan`, `Image`, `Profile`: property access, statistics, arithmetic, readable
//! printing. Large arrays sit behind `Arc`, so passing them around in scripts is cheap.

use super::registry::{binding_list, fail, int, num, properties, Doc, RResult, Registrar};
use super::values::register_printable;
pub use super::values::{
    register_types, show_custom, CurveRef, FilamentRef, FitRef, ImageRef, ProfileRef, ScanRef,
    TemplateRef, TEMPLATE_ARG,
};
use crate::data::{Image, Profile, ScanStatus};
use ndarray::Array2;
use rhai::{Array, Dynamic, Map, INT};
use std::fmt;
use std::sync::Arc;

/// Statistics over the finite values (unmeasured NaN pixels are skipped).
#[derive(Debug, Clone, Copy)]
pub struct Stats {
    pub n: usize,
    pub n_nan: usize,
    pub min: f64,
    pub max: f64,
    pub mean: f64,
    pub std: f64,
    pub abs_max: f64,
}

pub fn stats<'a>(values: impl Iterator<Item = &'a f64>) -> Stats {
    let (mut n, mut n_nan, mut min, mut max, mut sum, mut sum2) =
        (0usize, 0usize, f64::INFINITY, f64::NEG_INFINITY, 0.0, 0.0);
    for &v in values {
        if v.is_finite() {
            n += 1;
            min = min.min(v);
            max = max.max(v);
            sum += v;
            sum2 += v * v;
        } else {
            n_nan += 1;
        }
    }
    let mean = if n > 0 { sum / n as f64 } else { f64::NAN };
    let var = if n > 0 {
        (sum2 / n as f64 - mean * mean).max(0.0)
    } else {
        f64::NAN
    };
    Stats {
        n,
        n_nan,
        min,
        max,
        mean,
        std: var.sqrt(),
        abs_max: min.abs().max(max.abs()),
    }
}

fn checked_stats<'a>(who: &str, values: impl Iterator<Item = &'a f64>) -> RResult<Stats> {
    let s = stats(values);
    if s.n == 0 {
        return fail(format!(
            "{who}: no measured (finite) values: every pixel is NaN or the data is empty"
        ));
    }
    Ok(s)
}

fn g(v: f64) -> String {
    if v == 0.0 || (1e-3..1e5).contains(&v.abs()) {
        let s = format!("{v:.4}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        s.to_string()
    } else {
        format!("{v:.4e}")
    }
}

fn axis_desc(name: &str, a: &[f64]) -> String {
    match a {
        [] => format!("{name}: empty"),
        [v] => format!("{name} = {} µm", g(*v)),
        _ => format!("{name}: {} … {} µm", g(a[0]), g(a[a.len() - 1])),
    }
}

impl fmt::Display for ImageRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let i = &self.0;
        let s = stats(i.data.iter());
        write!(
            f,
            "Image {}×{} (rows × cols; {}, {})",
            i.rows(),
            i.cols(),
            axis_desc(&i.y_name, &i.y),
            axis_desc(&i.x_name, &i.x)
        )?;
        if s.n > 0 {
            write!(
                f,
                " min {} max {} mean {} std {}",
                g(s.min),
                g(s.max),
                g(s.mean),
                g(s.std)
            )?;
        }
        if s.n_nan > 0 {
            write!(f, " ({} unmeasured NaN pixels)", s.n_nan)?;
        }
        Ok(())
    }
}

impl fmt::Display for ProfileRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.0;
        let s = stats(p.v.iter());
        write!(
            f,
            "Profile of {} points ({})",
            p.v.len(),
            axis_desc(&p.t_name, &p.t)
        )?;
        if s.n > 0 {
            write!(f, " min {} max {} mean {}", g(s.min), g(s.max), g(s.mean))?;
        }
        if s.n_nan > 0 {
            write!(f, " ({} NaN)", s.n_nan)?;
        }
        Ok(())
    }
}

pub fn status_name(s: ScanStatus) -> &'static str {
    match s {
        ScanStatus::Complete => "complete",
        ScanStatus::Aborted => "aborted",
        ScanStatus::Failed => "failed",
    }
}

impl fmt::Display for ScanRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = &self.scan;
        let kind = s.meta["plan"]["kind"].as_str().unwrap_or("scan");
        write!(
            f,
            "Scan {kind} {}×{} ({}, {}), status {}",
            s.sx.rows(),
            s.sx.cols(),
            axis_desc(&s.sx.y_name, &s.sx.y),
            axis_desc(&s.sx.x_name, &s.sx.x),
            status_name(s.status)
        )?;
        for (n, im) in [("sx", &s.sx), ("sy", &s.sy), ("sz", &s.sz)] {
            let st = stats(im.data.iter());
            if st.n > 0 {
                write!(f, "; {n} [{}, {}]", g(st.min), g(st.max))?;
            }
        }
        if let Some(t) = s.meta["time"]["instrument_s"].as_f64() {
            write!(
                f,
                "; instrument time {}",
                crate::acquire::plan::fmt_seconds(t)
            )?;
        }
        if let Some(p) = &self.path {
            write!(f, "; saved to {p}")?;
        }
        Ok(())
    }
}

/// JSON → Rhai value (maps, arrays, numbers, strings, bools, `()` for null).
pub fn json_to_dynamic(v: &serde_json::Value) -> Dynamic {
    use serde_json::Value as J;
    match v {
        J::Null => Dynamic::UNIT,
        J::Bool(b) => Dynamic::from(*b),
        J::Number(n) => match n.as_i64() {
            Some(i) => Dynamic::from(i as INT),
            None => Dynamic::from(n.as_f64().unwrap_or(f64::NAN)),
        },
        J::String(s) => Dynamic::from(s.clone()),
        J::Array(a) => Dynamic::from_array(a.iter().map(json_to_dynamic).collect()),
        J::Object(o) => {
            let mut m = Map::new();
            for (k, v) in o {
                m.insert(k.as_str().into(), json_to_dynamic(v));
            }
            Dynamic::from_map(m)
        }
    }
}

/// Rhai value → JSON (for metadata written by scripts).
pub fn dynamic_to_json(v: &Dynamic) -> serde_json::Value {
    use serde_json::Value as J;
    if v.is_unit() {
        J::Null
    } else if let Ok(b) = v.as_bool() {
        J::Bool(b)
    } else if let Ok(i) = v.as_int() {
        J::from(i)
    } else if let Ok(f) = v.as_float() {
        J::from(f)
    } else if v.is_string() {
        J::String(v.to_string())
    } else if let Some(a) = v.read_lock::<Array>() {
        J::Array(a.iter().map(dynamic_to_json).collect())
    } else if let Some(m) = v.read_lock::<Map>() {
        J::Object(
            m.iter()
                .map(|(k, v)| (k.to_string(), dynamic_to_json(v)))
                .collect(),
        )
    } else {
        J::String(show(v))
    }
}

pub fn floats(v: &[f64]) -> Array {
    v.iter().map(|x| Dynamic::from(*x)).collect()
}

/// How the REPL and `eval` print a value.
pub fn show(v: &Dynamic) -> String {
    show_inner(v, true)
}

fn show_inner(v: &Dynamic, top: bool) -> String {
    if let Some(s) = v.read_lock::<ScanRef>() {
        return s.to_string();
    }
    if let Some(s) = v.read_lock::<ImageRef>() {
        return s.to_string();
    }
    if let Some(s) = v.read_lock::<ProfileRef>() {
        return s.to_string();
    }
    if let Some(s) = show_custom(v) {
        return s;
    }
    if let Some(a) = v.read_lock::<Array>() {
        const MAX: usize = 24;
        let mut items: Vec<String> = a.iter().take(MAX).map(|x| show_inner(x, false)).collect();
        if a.len() > MAX {
            items.push(format!("… ({} items)", a.len()));
        }
        return format!("[{}]", items.join(", "));
    }
    if let Some(m) = v.read_lock::<Map>() {
        let items: Vec<String> = m
            .iter()
            .map(|(k, x)| match super::units::printed_unit(k) {
                // a float under a bare key with a unit (`x`, `z_best`, `sens`): value and unit;
                // an integer there is a number, not a length (a Madlib axis number `x: 1`)
                Some(u) if x.is_float() => {
                    format!("{k}: {} {u}", show_inner(x, false))
                }
                _ => format!("{k}: {}", show_inner(x, false)),
            })
            .collect();
        let one = format!("#{{{}}}", items.join(", "));
        // a long result map at the prompt (status(), protocol results): one key per line
        if top && one.chars().count() > 100 {
            return format!("#{{\n  {}\n}}", items.join(",\n  "));
        }
        return one;
    }
    if v.is_string() && !top {
        return format!("{v:?}");
    }
    if v.is_unit() {
        return if top { String::new() } else { "()".into() };
    }
    if let Ok(x) = v.as_float() {
        return show_float(x);
    }
    v.to_string()
}

/// A float for people: 6 significant digits (`0.05`, not `0.049999999999999996`); integral
/// values keep a `.0` so floats stay recognisable.
pub fn show_float(x: f64) -> String {
    if x.is_finite() && x.fract() == 0.0 && x.abs() < 1e15 {
        return format!("{x:.1}");
    }
    super::words::fmt_num(x)
}

fn image_from(like: &Image, data: Array2<f64>) -> ImageRef {
    ImageRef(Arc::new(Image {
        data,
        x: like.x.clone(),
        y: like.y.clone(),
        x_name: like.x_name.clone(),
        y_name: like.y_name.clone(),
        flags: like.flags.clone(),
    }))
}

/// `img op img2`: the result with the clipped and dark pixels of both.
fn image_from2(a: &Image, b: &Image, data: Array2<f64>) -> ImageRef {
    let mut out = image_from(a, data);
    if let Some(fb) = &b.flags {
        let f = match &a.flags {
            Some(fa) => fa.union(fb),
            None => (**fb).clone(),
        };
        Arc::make_mut(&mut out.0).flags = Some(Arc::new(f));
    }
    out
}

/// A scan's channel as a script image, carrying its clipped and dark pixels
/// (`data::clip::PixelFlags`) so that analyses of the image flag them.
pub(crate) fn flagged_channel(scan: &crate::data::Scan, name: &str) -> Option<Image> {
    let mut im = scan.channel(name)?.clone();
    let key = match name {
        "x" => "sx",
        "y" => "sy",
        "z" => "sz",
        n => n,
    };
    im.flags = crate::data::clip::PixelFlags::of_channel(scan, key).map(Arc::new);
    Some(im)
}

fn same_shape(op: &str, a: &Image, b: &Image) -> RResult<()> {
    if a.data.dim() != b.data.dim() {
        return fail(format!(
            "img {op} img2: image shapes differ: {}×{} vs {}×{} (rows × cols)",
            a.rows(),
            a.cols(),
            b.rows(),
            b.cols()
        ));
    }
    Ok(())
}

fn index(who: &str, name: &str, i: &Dynamic, len: usize) -> RResult<usize> {
    let i = int(who, name, i)?;
    if i < 0 || i as usize >= len {
        return fail(format!(
            "{who}: {name} = {i} is out of range: 0 ≤ {name} ≤ {}",
            len as i64 - 1
        ));
    }
    Ok(i as usize)
}

const SCAN_EX: &str = "let s = scan_xy(#{x: [-0.5, 0.5], y: [-0.25, 0.25], nx: 11, ny: 5});";

pub fn register(r: &mut Registrar) {
    register_types(r.engine());
    register_printable::<ScanRef>(r.engine(), "Scan");
    register_printable::<ImageRef>(r.engine(), "Image");
    register_printable::<ProfileRef>(r.engine(), "Profile");
    register_scan(r);
    register_image(r);
    register_profile(r);
}

fn register_scan(r: &mut Registrar) {
    for (ch, what) in [
        ("sx", "Sx (x-difference signal)"),
        ("sy", "Sy (y-difference signal)"),
        ("sz", "Sz (sum signal)"),
    ] {
        let d = Doc::property("Scan", ch)
            .returns(
                "Image",
                &format!("the {what} channel; columns along scan.x, rows along scan.y (µm)"),
            )
            .summary(&format!("{what} image of the scan"))
            .example(&format!("{SCAN_EX} s.{ch}.cols"), "11");
        r.getter(d, move |s: &mut ScanRef| scan_channel(s, ch));
    }
    r.getter(
        Doc::property("Scan", "x")
            .returns(
                "array",
                "µm, one value per column (absolute stage positions)",
            )
            .summary("horizontal (column) axis of the scan, µm")
            .help("For XZ scans the columns are x; for YZ scans y. `scan.axes` names them.")
            .example(&format!("{SCAN_EX} s.x[0]"), "-0.5"),
        |s: &mut ScanRef| floats(&s.scan.sx.x),
    );
    properties!(r, "Scan", ScanRef, SCAN_EX, [
        y: "array", "µm, one value per row (absolute stage positions)"; "vertical (row) axis of the scan, µm (z for XZ/YZ scans)"; "s.y[4]" => "0.25"; |s| floats(&s.scan.sx.y),
        axes: "array", "[column axis, row axis], e.g. [\"x\", \"z\"]"; "names of the column and row axes"; "s.axes" => "[\"x\", \"y\"]"; |s| scan_axes(s),
        rows: "int", ""; "number of rows"; "s.rows" => "5"; |s| s.scan.sx.rows() as INT,
        cols: "int", ""; "number of columns"; "s.cols" => "11"; |s| s.scan.sx.cols() as INT,
    ]);
    r.getter(
        Doc::property("Scan", "meta")
            .returns("map", "plan, optics, instrument, scene, script path and sha256, git revision, time (wall and instrument), status")
            .summary("the scan's metadata")
            .example(&format!("{SCAN_EX} s.meta.points_total"), "55")
            .example(&format!("{SCAN_EX} s.meta.plan.kind"), "\"scan_xy\""),
        |s: &mut ScanRef| json_to_dynamic(&s.scan.meta),
    );
    properties!(r, "Scan", ScanRef, SCAN_EX, [
        status: "string", "\"complete\", \"aborted\" (Ctrl-C) or \"failed\" (device error)"; "whether the scan ran to its end"; "s.status" => "\"complete\""; |s| status_name(s.scan.status).to_string(),
        path: "string", "file path, or () if not saved"; "where the scan was (auto)saved"; "s.path.ends_with(\".npz\")" => "true"; |s| scan_path(s),
    ]);
    r.bind(
        Doc::method("Scan", "channel")
            .arg("name", "string", "", "\"sx\", \"sy\" or \"sz\"")
            .returns("Image", "")
            .summary("one channel by name")
            .example(&format!("{SCAN_EX} s.channel(\"sz\").rows"), "5")
            .example(
                &format!("{SCAN_EX} s.channel(\"sq\")"),
                "error: channel = \"sq\"",
            ),
        |s: &mut ScanRef, name: &str| scan_channel_named(s, name),
    );
}

/// The image the `Image` examples read: the mock signal on a 21×21 grid.
const IMG: &str = "let img = scan_xy(#{x: [-0.5, 0.5], y: [-0.5, 0.5], nx: 21, ny: 21}).sx;";

binding_list! {
    fn register_image {
        bind_image_properties, bind_image_sums, bind_image_pixels, bind_image_crop, bind_image_arithmetic
    }
}

/// `Image`'s shape and axes, and its statistics (`max`, `min`, …).
fn bind_image_properties(r: &mut Registrar) {
    properties!(r, "Image", ImageRef, IMG, [
        rows: "int", ""; "number of rows"; "img.rows" => "21"; |i| i.0.rows() as INT,
        cols: "int", ""; "number of columns"; "img.cols" => "21"; |i| i.0.cols() as INT,
        x: "array", "µm"; "column axis (pixel centres), µm"; "img.x[20]" => "0.5"; |i| floats(&i.0.x),
        y: "array", "µm"; "row axis (pixel centres), µm"; "img.y[0]" => "-0.5"; |i| floats(&i.0.y),
        dx: "float", "µm"; "pixel spacing along the columns, µm"; "img.dx" => "0.05"; |i| i.0.dx(),
        dy: "float", "µm"; "pixel spacing along the rows, µm"; "img.dy" => "0.05"; |i| i.0.dy(),
    ]);
    // expected values checked independently with numpy (mock signal on a 21×21 grid)
    let whats = stat_whats("pixel value", " of the pixel values");
    let expected = ["0.1709", "-0.1709", "0.0", "0.0915", "0.1709"];
    let doc = |name: &str, what: &str, ex_val: &str| {
        Doc::method("Image", name)
            .returns("float", "signal units")
            .summary(&format!("{what} (NaN pixels skipped)"))
            .help("Unmeasured (NaN) pixels of a partial scan are skipped; an image without any finite pixel is an error.")
            .example(&format!("{IMG} round(img.{name}() * 1e4) / 1e4"), ex_val)
    };
    register_stats(r, whats, expected, doc, "img", image_stat);
}

/// `Image.sum`, `abs`, `argmax`.
fn bind_image_sums(r: &mut Registrar) {
    r.bind(
        Doc::method("Image", "sum")
            .returns("float", "")
            .summary("sum of the finite pixel values")
            .example(
                &format!("{IMG} round(img.abs().sum() * 100.0) / 100.0"),
                "34.83",
            ),
        |i: &mut ImageRef| image_sum(i),
    );
    r.bind(
        Doc::method("Image", "abs")
            .returns("Image", "")
            .summary("absolute value of every pixel")
            .example(&format!("{IMG} img.abs().min() >= 0.0"), "true"),
        |i: &mut ImageRef| image_from(&i.0, i.0.data.mapv(f64::abs)),
    );
    r.bind(
        Doc::method("Image", "argmax")
            .returns(
                "map",
                "#{row, col, x, y, v}: indices, position (µm) and value of the largest pixel",
            )
            .summary("where the largest pixel is")
            .example(
                &format!("{IMG} let m = img.argmax(); [m.row, m.col]"),
                "[10, 16]",
            ),
        |i: &mut ImageRef| image_argmax(i),
    );
}

/// `Image.at`, `row`, `col`: pixels and lines.
fn bind_image_pixels(r: &mut Registrar) {
    r.bind(
        Doc::method("Image", "at")
            .arg("i", "int", "", "row index, 0 ≤ i < rows")
            .arg("j", "int", "", "column index, 0 ≤ j < cols")
            .returns("float", "")
            .summary("one pixel value")
            .example(&format!("{IMG} img.at(10, 10)"), "0.0")
            .example(
                &format!("{IMG} img.at(21, 0)"),
                "error: i = 21 is out of range: 0 ≤ i ≤ 20",
            ),
        |im: &mut ImageRef, i: Dynamic, j: Dynamic| image_at(im, &i, &j),
    );
    r.bind(
        Doc::method("Image", "row")
            .arg("i", "int", "", "row index, 0 ≤ i < rows")
            .returns("Profile", "along the column axis (µm)")
            .summary("one row as a profile")
            .example(&format!("{IMG} img.row(10).len"), "21")
            .example(
                &format!("{IMG} img.row(-1)"),
                "error: i = -1 is out of range",
            ),
        |im: &mut ImageRef, i: Dynamic| image_row(im, &i),
    );
    r.bind(
        Doc::method("Image", "col")
            .arg("j", "int", "", "column index, 0 ≤ j < cols")
            .returns("Profile", "along the row axis (µm)")
            .summary("one column as a profile")
            .example(&format!("{IMG} img.col(3).t[0]"), "-0.5"),
        |im: &mut ImageRef, j: Dynamic| image_col(im, &j),
    );
}

/// `Image.crop`, `to_array`.
fn bind_image_crop(r: &mut Registrar) {
    r.bind(
        Doc::method("Image", "crop")
            .arg("r0", "int", "", "first row")
            .arg("r1", "int", "", "last row (inclusive)")
            .arg("c0", "int", "", "first column")
            .arg("c1", "int", "", "last column (inclusive)")
            .returns("Image", "with the matching axes")
            .summary("a rectangular slice by pixel indices (inclusive)")
            .example(
                &format!("{IMG} let c = img.crop(5, 15, 0, 9); [c.rows, c.cols, c.x[0]]"),
                "[11, 10, -0.5]",
            ),
        |im: &mut ImageRef, r0: Dynamic, r1: Dynamic, c0: Dynamic, c1: Dynamic| {
            image_crop(im, [&r0, &r1, &c0, &c1])
        },
    );
    r.bind(
        Doc::method("Image", "to_array")
            .returns("array", "array of rows, each an array of floats")
            .summary("pixel values as nested arrays (for small images)")
            .example(&format!("{IMG} img.crop(0, 1, 0, 2).to_array().len"), "2"),
        |im: &mut ImageRef| image_to_array(im),
    );
}

/// `Image` arithmetic: `+ - * /` with images and numbers.
fn bind_image_arithmetic(r: &mut Registrar) {
    r.declare(
        Doc::operator("Image", "arithmetic")
            .form("img + img2, img - img2, img * img2, img / img2, img * 2.0, 2.0 * img, img + 1, img / 4, -img")
            .returns("Image", "with the axes of the left image")
            .summary("pixel-wise arithmetic with another image of the same shape or a number")
            .example(&format!("{IMG} (img * 2.0).max() / img.max()"), "2.0")
            .example(&format!("{IMG} (img - img).abs_max()"), "0.0")
            .example(&format!("{IMG} img - img.crop(0, 1, 0, 1)"), "error: image shapes differ: 21×21 vs 2×2"),
    );
    macro_rules! ops {
        ($($op:tt),*) => {$(
            let e = r.engine();
            e.register_fn(stringify!($op), |a: ImageRef, b: ImageRef| -> RResult<ImageRef> {
                same_shape(stringify!($op), &a.0, &b.0)?;
                Ok(image_from2(&a.0, &b.0, &a.0.data $op &b.0.data))
            });
            e.register_fn(stringify!($op), |a: ImageRef, b: f64| image_from(&a.0, a.0.data.mapv(|v| v $op b)));
            e.register_fn(stringify!($op), |a: ImageRef, b: INT| image_from(&a.0, a.0.data.mapv(|v| v $op b as f64)));
            e.register_fn(stringify!($op), |b: f64, a: ImageRef| image_from(&a.0, a.0.data.mapv(|v| b $op v)));
            e.register_fn(stringify!($op), |b: INT, a: ImageRef| image_from(&a.0, a.0.data.mapv(|v| b as f64 $op v)));
        )*};
    }
    ops!(+, -, *, /);
    r.engine()
        .register_fn("-", |a: ImageRef| image_from(&a.0, a.0.data.mapv(|v| -v)));
}

fn register_profile(r: &mut Registrar) {
    const P: &str = "let p = scan_line(#{axis: \"x\", from: -1.0, to: 1.0, n: 41}).sx.row(0);";
    properties!(r, "Profile", ProfileRef, P, [
        t: "array", "µm (or as named by the profile)"; "positions of the samples"; "p.t[40]" => "1.0"; |p| floats(&p.0.t),
        v: "array", "signal units"; "values of the samples"; "p.v.len" => "41"; |p| floats(&p.0.v),
        len: "int", ""; "number of samples"; "p.len" => "41"; |p| p.0.v.len() as INT,
    ]);
    let whats = stat_whats("value", "");
    let expected = ["0.1709", "-0.1709", "0.0", "0.0989", "0.1709"];
    let doc = |name: &str, what: &str, ex: &str| {
        Doc::method("Profile", name)
            .returns("float", "")
            .summary(&format!(
                "{what} (NaN samples skipped); also a property: profile.{name}"
            ))
            .example(&format!("{P} round(p.{name}() * 1e4) / 1e4"), ex)
    };
    register_stats(r, whats, expected, doc, "profile", profile_stat);
    r.bind(
        Doc::method("Profile", "argmax")
            .returns("float", "µm")
            .summary("position t of the largest value")
            .example(&format!("{P} round(p.argmax() * 1000.0) / 1000.0"), "0.3"),
        |p: &mut ProfileRef| profile_argmax(p),
    );
    r.bind(
        Doc::func("profile")
            .arg("t", "array", "µm", "sample positions")
            .arg("v", "array", "", "values (same length)")
            .returns("Profile", "")
            .summary("make a profile from two arrays of numbers")
            .example("profile([0, 1, 2], [1.0, 3.0, 2.0]).argmax()", "1.0")
            .example(
                "profile([0, 1], [1.0])",
                "error: t has 2 values but v has 1",
            ),
        |t: Array, v: Array| profile(&t, &v),
    );
}

/// The statistics (max, min, mean, std, abs_max) of a binding, as a function of [`Stats`].
type StatFn = fn(&Stats) -> f64;

/// The statistics bound on Image and Profile, in the order of their declarations.
const STATS: [(&str, StatFn); 5] = [
    ("max", |s| s.max),
    ("min", |s| s.min),
    ("mean", |s| s.mean),
    ("std", |s| s.std),
    ("abs_max", |s| s.abs_max),
];

/// What each of [`STATS`] is of a type whose values are `value`s (`std_of`: what the standard
/// deviation's help adds, e.g. " of the pixel values").
fn stat_whats(value: &str, std_of: &str) -> [String; 5] {
    [
        format!("largest {value}"),
        format!("smallest {value}"),
        format!("mean {value}"),
        format!("standard deviation{std_of} (population)"),
        format!("largest absolute {value}"),
    ]
}

/// The statistics of a script type `T` (Image, Profile) as methods `value.name()` declared by
/// `doc(name, what, expected example value)` and, undeclared, as the same properties
/// `value.name`: one of each of [`STATS`], with `whats` and `expected` in its order.
/// `stat(who, value, f)` computes one; `who` (`receiver.name()` or `receiver.name`) names the
/// call in its errors.
fn register_stats<T: super::registry::Value>(
    r: &mut Registrar,
    whats: [String; 5],
    expected: [&str; 5],
    doc: impl Fn(&str, &str, &str) -> Doc,
    receiver: &str,
    stat: fn(&str, &T, StatFn) -> RResult<f64>,
) {
    for (((name, f), what), expected) in STATS.into_iter().zip(whats).zip(expected) {
        let who = format!("{receiver}.{name}()");
        r.bind(doc(name, &what, expected), move |v: &mut T| {
            stat(&who, v, f)
        });
        // the same as a property (`img.max`)
        let who = format!("{receiver}.{name}");
        r.engine()
            .register_get(name, move |v: &mut T| stat(&who, v, f));
    }
}

/// `scan.sx` / `scan.sy` / `scan.sz`: one channel as an Image.
fn scan_channel(s: &ScanRef, ch: &str) -> ImageRef {
    ImageRef(Arc::new(
        flagged_channel(&s.scan, ch).unwrap_or_else(|| s.scan.sx.clone()),
    ))
}

/// `scan.axes`: the names of the column and row axes.
fn scan_axes(s: &ScanRef) -> Array {
    vec![
        s.scan.sx.x_name.clone().into(),
        s.scan.sx.y_name.clone().into(),
    ]
}

/// `scan.path`: where the scan was saved, or () if it was not.
fn scan_path(s: &ScanRef) -> Dynamic {
    s.path
        .as_ref()
        .map(|p| Dynamic::from(p.to_string()))
        .unwrap_or(Dynamic::UNIT)
}

/// `scan.channel(name)`: one channel by name ("sx", "sy", "sz").
fn scan_channel_named(s: &ScanRef, name: &str) -> RResult<ImageRef> {
    match flagged_channel(&s.scan, name) {
        Some(i) => Ok(ImageRef(Arc::new(i))),
        None => fail(format!(
            "scan.channel: channel = {name:?} is not one of \"sx\", \"sy\", \"sz\""
        )),
    }
}

/// `img.max()` and the other statistics `f` of the finite pixels (`who` names the call).
fn image_stat(who: &str, i: &ImageRef, f: StatFn) -> RResult<f64> {
    Ok(f(&checked_stats(who, i.0.data.iter())?))
}

/// `img.sum()`: the sum of the finite pixel values.
fn image_sum(i: &ImageRef) -> f64 {
    i.0.data.iter().filter(|v| v.is_finite()).sum()
}

/// `img.argmax()`: #{row, col, x, y, v} of the largest finite pixel (x, y in µm).
fn image_argmax(i: &ImageRef) -> RResult<Map> {
    let mut best: Option<(usize, usize, f64)> = None;
    for ((r, c), &v) in i.0.data.indexed_iter() {
        if v.is_finite() && best.is_none_or(|b| v > b.2) {
            best = Some((r, c, v));
        }
    }
    let Some((r, c, v)) = best else {
        return fail("img.argmax(): no measured (finite) pixels");
    };
    let mut m = Map::new();
    m.insert("row".into(), (r as INT).into());
    m.insert("col".into(), (c as INT).into());
    m.insert("x".into(), i.0.x[c].into());
    m.insert("y".into(), i.0.y[r].into());
    m.insert("v".into(), v.into());
    Ok(m)
}

/// `img.at(i, j)`: the pixel of row i, column j.
fn image_at(im: &ImageRef, i: &Dynamic, j: &Dynamic) -> RResult<f64> {
    let i = index("img.at", "i", i, im.0.rows())?;
    let j = index("img.at", "j", j, im.0.cols())?;
    Ok(im.0.data[[i, j]])
}

/// `img.row(i)`: row i as a profile along the column axis.
fn image_row(im: &ImageRef, i: &Dynamic) -> RResult<ProfileRef> {
    let i = index("img.row", "i", i, im.0.rows())?;
    let mut p = Profile::new(im.0.x.clone(), im.0.data.row(i).to_vec());
    p.t_name = im.0.x_name.clone();
    Ok(ProfileRef(Arc::new(p)))
}

/// `img.col(j)`: column j as a profile along the row axis.
fn image_col(im: &ImageRef, j: &Dynamic) -> RResult<ProfileRef> {
    let j = index("img.col", "j", j, im.0.cols())?;
    let mut p = Profile::new(im.0.y.clone(), im.0.data.column(j).to_vec());
    p.t_name = im.0.y_name.clone();
    Ok(ProfileRef(Arc::new(p)))
}

/// `img.crop(r0, r1, c0, c1)`: rows r0..=r1 and columns c0..=c1, with their axes.
fn image_crop(im: &ImageRef, [r0, r1, c0, c1]: [&Dynamic; 4]) -> RResult<ImageRef> {
    let (nr, nc) = (im.0.rows(), im.0.cols());
    let r0 = index("img.crop", "r0", r0, nr)?;
    let r1 = index("img.crop", "r1", r1, nr)?;
    let c0 = index("img.crop", "c0", c0, nc)?;
    let c1 = index("img.crop", "c1", c1, nc)?;
    if r1 < r0 || c1 < c0 {
        return fail(format!(
            "img.crop: need r0 ≤ r1 and c0 ≤ c1, got rows {r0}..{r1}, cols {c0}..{c1}"
        ));
    }
    let data = im.0.data.slice(ndarray::s![r0..=r1, c0..=c1]).to_owned();
    let mut out = Image::new(data, im.0.x[c0..=c1].to_vec(), im.0.y[r0..=r1].to_vec())
        .with_axis_names(&im.0.x_name, &im.0.y_name);
    out.flags =
        im.0.flags
            .as_ref()
            .and_then(|f| f.crop((r0, r1), (c0, c1)).map(Arc::new));
    Ok(ImageRef(Arc::new(out)))
}

/// `img.to_array()`: the pixel values as an array of rows.
fn image_to_array(im: &ImageRef) -> Array {
    im.0.data
        .rows()
        .into_iter()
        .map(|r| Dynamic::from_array(r.iter().map(|v| Dynamic::from(*v)).collect()))
        .collect()
}

/// `profile.max()` and the other statistics `f` of the finite samples (`who` names the call).
fn profile_stat(who: &str, p: &ProfileRef, f: StatFn) -> RResult<f64> {
    Ok(f(&checked_stats(who, p.0.v.iter())?))
}

/// `profile.argmax()`: the position t of the largest finite value.
fn profile_argmax(p: &ProfileRef) -> RResult<f64> {
    let mut best: Option<(f64, f64)> = None;
    for (&t, &v) in p.0.t.iter().zip(&p.0.v) {
        if v.is_finite() && best.is_none_or(|b| v > b.1) {
            best = Some((t, v));
        }
    }
    best.map(|b| b.0)
        .ok_or_else(|| "profile.argmax(): no finite values".into())
}

/// `profile(t, v)`: a profile from positions t (µm) and values v of the same length.
fn profile(t: &Array, v: &Array) -> RResult<ProfileRef> {
    let t: Vec<f64> = t
        .iter()
        .enumerate()
        .map(|(i, x)| num("profile", &format!("t[{i}]"), x))
        .collect::<RResult<_>>()?;
    let v: Vec<f64> = v
        .iter()
        .enumerate()
        .map(|(i, x)| num("profile", &format!("v[{i}]"), x))
        .collect::<RResult<_>>()?;
    if t.len() != v.len() {
        return fail(format!(
            "profile: t has {} values but v has {}",
            t.len(),
            v.len()
        ));
    }
    Ok(ProfileRef(Arc::new(Profile::new(t, v))))
}

#[cfg(test)]
mod show_tests {
    use super::*;

    /// A float under a bare position key prints with µm; an integer there (a Madlib axis
    /// number in `status().instrument.stage.axes`) prints bare: `x: 1`, not `x: 1 µm`.
    #[test]
    fn integers_under_position_keys_print_without_a_unit() {
        let mut axes = Map::new();
        axes.insert("x".into(), Dynamic::from(1 as INT));
        axes.insert("y".into(), Dynamic::from(2 as INT));
        let mut pos = Map::new();
        pos.insert("x".into(), Dynamic::from(1.5f64));
        pos.insert("z".into(), Dynamic::from(-2.0f64));
        assert_eq!(show(&axes.into()), "#{x: 1, y: 2}");
        assert_eq!(show(&pos.into()), "#{x: 1.5 µm, z: -2.0 µm}");
    }
}
