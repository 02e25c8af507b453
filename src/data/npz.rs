//! Scans as NumPy `.npz` files (`numpy.load` reads them).
//!
//! Layout (one `.npy` member per array, deflate-compressed zip):
//!
//! | array  | dtype     | shape        | content                                   |
//! |--------|-----------|--------------|-------------------------------------------|
//! | `sx`   | `<f8`     | (rows, cols) | QPD x difference signal                   |
//! | `sy`   | `<f8`     | (rows, cols) | QPD y difference signal                   |
//! | `sz`   | `<f8`     | (rows, cols) | QPD sum signal                            |
//! | `x`    | `<f8`     | (cols,)      | horizontal axis, pixel centres, µm        |
//! | `y`    | `<f8`     | (rows,)      | vertical axis (y, or z for XZ/YZ), µm     |
//! | `meta` | `\|u1`    | (n,)         | UTF-8 JSON text of the metadata           |
//! | `raw_*` | `<f8`    | (rows, n)    | raster scans only: raw samples per line (see below) |
//! | `clipped_s*` | `<u4` | (rows, cols) | only when clipped: samples at the input's rail per pixel |
//! | `dark`  | `\|u1`   | (rows, cols) | only when dark: 1 where the sum was below the floor |
//!
//! Python: `m = json.loads(f["meta"].tobytes())`. The JSON object holds the reserved keys
//! `format` (`"bfpscope-scan"`), `format_version` (1), `status` (`"complete"`, `"aborted"`,
//! `"failed"`), `x_name`, `y_name`, and next to them the scan's own metadata keys (plan, optics,
//! instrument, scene, script, time, ...). If the scan's metadata is not a JSON object, or uses a
//! reserved key itself, it is stored whole under `user_meta` instead, so loading always gives
//! back exactly what was saved. Unmeasured pixels (aborted scans) are NaN.
//!
//! A scan with clipped or dark pixels keeps their flags (see `data::clip`): `clipped_sx`,
//! `clipped_sy`, `clipped_sz` (`<u4`, rows × cols: the digitiser samples of that pixel at or
//! beyond the input's rail), each written only when that channel has a clipped sample, and
//! `dark` (`|u1`, rows × cols, 1 where the sum was below the floor), written only when a pixel
//! is dark. `meta.clipped` and `meta.dark` summarise them (and are there, with zeros, whenever
//! the QPD knew its range).
//!
//! A hardware-timed raster scan keeps what it binned, one row per line, NaN after a line's
//! last sample: `raw_sx`, `raw_sy`, `raw_sz` (the digitiser's samples), `raw_position_um`
//! (the stage's measured position at each digitiser sample, interpolated from the recorder),
//! `raw_record_target_um` and `raw_record_position_um` (the recorder's own samples). Their
//! time bases are in `meta.raster`.

use super::{atomic_write, image::Image, DataError, Scan, ScanStatus};
use ndarray::{Array1, Array2};
use ndarray_npy::{NpzReader, NpzWriter, ReadNpzError};
use serde_json::{Map, Value};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

/// Value of the `format` key in the stored metadata.
pub const FORMAT_NAME: &str = "bfpscope-scan";
/// Value of the `format_version` key in the stored metadata.
pub const FORMAT_VERSION: u64 = 1;
/// Keys of the stored metadata that belong to the file format, not to the scan's metadata.
pub const RESERVED_META_KEYS: [&str; 6] = [
    "format",
    "format_version",
    "status",
    "x_name",
    "y_name",
    "user_meta",
];

/// The JSON object stored in the `meta` array of a scan file (see the module docs).
pub fn file_meta(scan: &Scan) -> Value {
    let mut m = Map::new();
    m.insert("format".into(), FORMAT_NAME.into());
    m.insert("format_version".into(), FORMAT_VERSION.into());
    m.insert("status".into(), scan.status.as_str().into());
    m.insert("x_name".into(), scan.sx.x_name.clone().into());
    m.insert("y_name".into(), scan.sx.y_name.clone().into());
    match &scan.meta {
        Value::Object(user)
            if !user
                .keys()
                .any(|k| RESERVED_META_KEYS.contains(&k.as_str())) =>
        {
            for (k, v) in user {
                m.insert(k.clone(), v.clone());
            }
        }
        other => {
            m.insert("user_meta".into(), other.clone());
        }
    }
    Value::Object(m)
}

/// Save a scan as `.npz` (atomically: temporary file in the same directory, then rename;
/// an existing file of that name is replaced only once the new one is complete).
///
/// The three channels must share shape and axes ([`Scan::check_consistent`]).
pub fn save_scan(path: impl AsRef<Path>, scan: &Scan) -> Result<(), DataError> {
    let path = path.as_ref();
    scan.check_consistent()?;
    atomic_write(path, |tmp| write_scan_npz(tmp, scan))
}

/// Write the `.npz` directly to `path` (no temporary; callers provide atomicity).
pub(crate) fn write_scan_npz(path: &Path, scan: &Scan) -> Result<(), DataError> {
    scan.check_consistent()?;
    let meta_bytes = serde_json::to_vec(&file_meta(scan))
        .map_err(|e| DataError::format(path, format!("cannot encode metadata as JSON: {e}")))?;
    let meta = Array1::from_vec(meta_bytes);
    let x = Array1::from_vec(scan.sx.x.clone());
    let y = Array1::from_vec(scan.sx.y.clone());
    let file = File::create(path).map_err(|e| DataError::io(path, e))?;
    let latch = Latch::new(file);
    let failed = latch.failed.clone();
    let werr = |e: ndarray_npy::WriteNpzError| DataError::format(path, format!("writing npz: {e}"));
    // the file's first write error (a full disk) ends the writing; the zip writer then closes on
    // a writer that takes everything, so nothing prints "ZipWriter drop failed" on stderr
    let io_err = || failed.borrow_mut().take().map(|e| DataError::io(path, e));
    let mut npz = NpzWriter::new_compressed(BufWriter::new(latch));
    // each array, then the file's first write error if there was one
    let mut add =
        |name: String, a: &dyn Fn(&mut Npz, String) -> Result<(), ndarray_npy::WriteNpzError>| {
            a(&mut npz, name).map_err(werr)?;
            io_err().map_or(Ok(()), Err)
        };
    add("sx".into(), &|n, name| n.add_array(name, &scan.sx.data))?;
    add("sy".into(), &|n, name| n.add_array(name, &scan.sy.data))?;
    add("sz".into(), &|n, name| n.add_array(name, &scan.sz.data))?;
    add("x".into(), &|n, name| n.add_array(name, &x))?;
    add("y".into(), &|n, name| n.add_array(name, &y))?;
    add("meta".into(), &|n, name| n.add_array(name, &meta))?;
    for (name, a) in &scan.raw {
        add(format!("raw_{name}"), &|n, name| n.add_array(name, a))?;
    }
    for (name, a) in super::clip::CLIPPED_ARRAYS.iter().zip(&scan.flags.clipped) {
        if let Some(a) = a {
            add(name.to_string(), &|n, name| n.add_array(name, a))?;
        }
    }
    if let Some(d) = &scan.flags.dark {
        add("dark".into(), &|n, name| n.add_array(name, d))?;
    }
    let buf = npz.finish().map_err(werr)?;
    buf.into_inner()
        .map_err(|e| DataError::io(path, e.into_error()))?;
    io_err().map_or(Ok(()), Err)
}

/// The zip writer of a scan file.
type Npz = NpzWriter<BufWriter<Latch>>;

/// A file that keeps its first write error and from then on takes every write and seek without
/// doing it (keeping the position a file would have): a full disk ends the writing with that
/// error in words, and the zip writer closing on it (its `Drop` finishes the archive, printing
/// any error raw on stderr) finds nothing to complain about.
struct Latch {
    file: File,
    failed: std::rc::Rc<std::cell::RefCell<Option<std::io::Error>>>,
    /// The position and the length the file has (or would have had), bytes.
    pos: u64,
    len: u64,
}

impl Latch {
    fn new(file: File) -> Latch {
        Latch {
            file,
            failed: Default::default(),
            pos: 0,
            len: 0,
        }
    }
    fn is_failed(&self) -> bool {
        self.failed.borrow().is_some()
    }
    fn fail(&mut self, e: std::io::Error) {
        self.failed.borrow_mut().get_or_insert(e);
    }
}

impl std::io::Write for Latch {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if !self.is_failed() {
            if let Err(e) = self.file.write_all(buf) {
                self.fail(e);
            }
        }
        self.pos += buf.len() as u64;
        self.len = self.len.max(self.pos);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        if !self.is_failed() {
            if let Err(e) = self.file.flush() {
                self.fail(e);
            }
        }
        Ok(())
    }
}

impl std::io::Seek for Latch {
    fn seek(&mut self, to: std::io::SeekFrom) -> std::io::Result<u64> {
        use std::io::SeekFrom;
        let p = match to {
            SeekFrom::Start(n) => Some(n),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
            SeekFrom::End(d) => self.len.checked_add_signed(d),
        };
        let Some(p) = p else {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "seek before the start of the file",
            ));
        };
        if !self.is_failed() {
            if let Err(e) = self.file.seek(SeekFrom::Start(p)) {
                self.fail(e);
            }
        }
        self.pos = p;
        Ok(p)
    }
}

/// Load a scan written by [`save_scan`] (or any `.npz` with float arrays `sx`, `sy`, `sz`, `x`,
/// `y`; `meta` is optional, float32 arrays are widened to float64).
pub fn load_scan(path: impl AsRef<Path>) -> Result<Scan, DataError> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| DataError::io(path, e))?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(1);
    if len == 0 {
        return Err(DataError::format(
            path,
            "empty file: a reserved scan slot that was never written (the save did not complete)",
        ));
    }
    let mut npz = NpzReader::new(file)
        .map_err(|e| DataError::format(path, format!("not a readable .npz file: {e}")))?;
    let names = npz
        .names()
        .map_err(|e| DataError::format(path, format!("cannot list the arrays: {e}")))?;
    let has = |n: &str| names.iter().any(|m| m == n || m == &format!("{n}.npy"));
    for required in ["sx", "sy", "sz", "x", "y"] {
        if !has(required) {
            return Err(DataError::format(
                path,
                format!(
                    "array `{required}` is missing (found: {})",
                    names.join(", ")
                ),
            ));
        }
    }
    let sx: Array2<f64> = read_f64(&mut npz, path, "sx")?;
    let sy: Array2<f64> = read_f64(&mut npz, path, "sy")?;
    let sz: Array2<f64> = read_f64(&mut npz, path, "sz")?;
    let x: Array1<f64> = read_f64(&mut npz, path, "x")?;
    let y: Array1<f64> = read_f64(&mut npz, path, "y")?;
    for (name, a) in [("sy", &sy), ("sz", &sz)] {
        if a.dim() != sx.dim() {
            return Err(DataError::format(
                path,
                format!(
                    "array `{name}` has shape {:?} but `sx` has {:?}",
                    a.dim(),
                    sx.dim()
                ),
            ));
        }
    }
    if x.len() != sx.ncols() || y.len() != sx.nrows() {
        return Err(DataError::format(
            path,
            format!(
                "axes do not match the images: `x` has {} values, `y` {}, images are {}x{} (rows x cols)",
                x.len(),
                y.len(),
                sx.nrows(),
                sx.ncols()
            ),
        ));
    }

    let (status, x_name, y_name, meta) = if has("meta") {
        let bytes: Array1<u8> = npz
            .by_name("meta")
            .map_err(|e| DataError::format(path, format!("array `meta`: {e}")))?;
        let text = String::from_utf8(bytes.to_vec())
            .map_err(|e| DataError::format(path, format!("`meta` is not UTF-8 text: {e}")))?;
        let stored: Value = serde_json::from_str(&text)
            .map_err(|e| DataError::format(path, format!("`meta` is not valid JSON: {e}")))?;
        split_file_meta(path, stored)?
    } else {
        (
            ScanStatus::Complete,
            "x".to_string(),
            "y".to_string(),
            Value::Object(Map::new()),
        )
    };

    let mut raw = Vec::new();
    for n in &names {
        let n = n.strip_suffix(".npy").unwrap_or(n);
        if let Some(name) = n.strip_prefix("raw_") {
            let a: Array2<f64> = read_f64(&mut npz, path, n)?;
            raw.push((name.to_string(), a));
        }
    }
    let mut flags = super::clip::InputFlags::default();
    let shape_ok = |name: &str, dim: (usize, usize)| {
        if dim == sx.dim() {
            Ok(())
        } else {
            Err(DataError::format(
                path,
                format!(
                    "array `{name}` has shape {dim:?} but `sx` has {:?}",
                    sx.dim()
                ),
            ))
        }
    };
    for (k, name) in super::clip::CLIPPED_ARRAYS.iter().enumerate() {
        if has(name) {
            let a: Array2<u32> = npz
                .by_name(name)
                .map_err(|e| DataError::format(path, format!("array `{name}`: {e}")))?;
            shape_ok(name, a.dim())?;
            flags.clipped[k] = Some(a);
        }
    }
    if has("dark") {
        let a: Array2<u8> = npz
            .by_name("dark")
            .map_err(|e| DataError::format(path, format!("array `dark`: {e}")))?;
        shape_ok("dark", a.dim())?;
        flags.dark = Some(a);
    }
    let (x, y) = (x.to_vec(), y.to_vec());
    let mk = |data| Image::new(data, x.clone(), y.clone()).with_axis_names(&x_name, &y_name);
    Ok(Scan {
        sx: mk(sx),
        sy: mk(sy),
        sz: mk(sz),
        status,
        meta,
        raw,
        flags,
    })
}

/// Undo [`file_meta`]: the file-format keys and the scan's own metadata.
fn split_file_meta(
    path: &Path,
    stored: Value,
) -> Result<(ScanStatus, String, String, Value), DataError> {
    let Value::Object(mut m) = stored else {
        return Err(DataError::format(path, "`meta` JSON is not an object"));
    };
    let status = match m.remove("status") {
        None => ScanStatus::Complete,
        Some(Value::String(s)) => ScanStatus::parse(&s)
            .map_err(|e| DataError::format(path, format!("`meta`.status: {e}")))?,
        Some(other) => {
            return Err(DataError::format(
                path,
                format!("`meta`.status is not a string: {other}"),
            ))
        }
    };
    let mut name = |key: &str, default: &str| match m.remove(key) {
        Some(Value::String(s)) => s,
        _ => default.to_string(),
    };
    let x_name = name("x_name", "x");
    let y_name = name("y_name", "y");
    if let Some(v) = m.remove("format_version") {
        if v.as_u64().is_none_or(|n| n > FORMAT_VERSION) {
            return Err(DataError::format(
                path,
                format!("scan file format version {v} is newer than this program reads ({FORMAT_VERSION})"),
            ));
        }
    }
    m.remove("format");
    let meta = match m.remove("user_meta") {
        Some(v) => v,
        None => Value::Object(m),
    };
    Ok((status, x_name, y_name, meta))
}

/// Read a float array, accepting float64 or (widened) float32.
fn read_f64<D: ndarray::Dimension>(
    npz: &mut NpzReader<File>,
    path: &Path,
    name: &str,
) -> Result<ndarray::Array<f64, D>, DataError> {
    let err = |e: ReadNpzError| DataError::format(path, format!("array `{name}`: {e}"));
    match npz.by_name::<ndarray::OwnedRepr<f64>, D>(name) {
        Ok(a) => Ok(a),
        Err(e64) => match npz.by_name::<ndarray::OwnedRepr<f32>, D>(name) {
            Ok(a) => Ok(a.mapv(f64::from)),
            Err(_) => Err(err(e64)),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn tiny(meta: Value) -> Scan {
        let img = Image::new(Array2::zeros((1, 2)), vec![0.0, 1.0], vec![0.0]);
        Scan::complete([img.clone(), img.clone(), img], meta)
    }

    #[test]
    fn object_meta_is_merged_and_split_back() {
        let s = tiny(json!({"plan": {"nx": 2}, "time": "now"}));
        let stored = file_meta(&s);
        assert_eq!(stored["plan"]["nx"], 2);
        assert_eq!(stored["status"], "complete");
        assert!(stored.get("user_meta").is_none());
        let (st, xn, yn, meta) = split_file_meta(Path::new("t"), stored).unwrap();
        assert_eq!(
            (st, xn.as_str(), yn.as_str()),
            (ScanStatus::Complete, "x", "y")
        );
        assert_eq!(meta, s.meta);
    }

    #[test]
    fn non_object_or_clashing_meta_goes_to_user_meta() {
        for meta in [Value::Null, json!([1, 2]), json!({"status": "device ok"})] {
            let s = tiny(meta.clone());
            let stored = file_meta(&s);
            assert_eq!(stored["user_meta"], meta);
            let (_, _, _, back) = split_file_meta(Path::new("t"), stored).unwrap();
            assert_eq!(back, meta);
        }
    }
}
