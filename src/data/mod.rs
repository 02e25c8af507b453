//! Scans, images, profiles and their files (npz, TIFF, CSV), and the session store.
//!
//! File formats are described for users in `docs/files.md`. Every writer in this module writes
//! to a temporary file in the destination directory and renames it into place, so a crash or a
//! full disk never leaves a half-written file under the final name (nothing measured is lost).

pub mod clip;
pub mod clock;
pub mod csv;
pub mod image;
pub mod npz;
pub mod provenance;
pub mod scan;
pub mod session;
pub mod tiff;

pub use self::csv::{load_csv_profile, load_csv_table, save_csv_profile, save_csv_table};
pub use self::image::{segment_lengths, Image, Profile, Stats};
pub use self::npz::{load_scan, save_scan};
pub use self::scan::{Scan, ScanStatus};
pub use self::session::Session;
pub use self::tiff::{load_tiff, save_tiff};

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Everything that can go wrong with images, profiles, their files and figures.
///
/// Messages name the argument, the offending value and what would have been allowed.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// An index outside `0..len`.
    #[error("{what} index {index} is out of range: valid indices are {}", valid_range(*.len))]
    IndexOutOfRange {
        what: &'static str,
        index: i64,
        len: usize,
    },

    /// Two operands of an element-wise operation differ in shape.
    #[error("{op}: shapes differ: left is {}x{} (rows x cols), right is {}x{}", .left.0, .left.1, .right.0, .right.1)]
    ShapeMismatch {
        op: &'static str,
        left: (usize, usize),
        right: (usize, usize),
    },

    /// A statistic of data that holds no finite value to work with.
    #[error("{what}: all {count} values are NaN")]
    AllNaN { what: String, count: usize },

    /// An operation on empty data.
    #[error("{0}: no data (empty)")]
    Empty(String),

    /// An argument outside its allowed range.
    #[error("invalid argument `{name}` = {value}: {allowed}")]
    InvalidArgument {
        name: String,
        value: String,
        allowed: String,
    },

    /// Reading or writing a file failed at the operating-system level.
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A file exists but its contents are not what the format requires.
    #[error("{}: {msg}", .path.display())]
    Format { path: PathBuf, msg: String },

    /// A figure could not be drawn.
    #[error("plot {}: {msg}", .path.display())]
    Plot { path: PathBuf, msg: String },
}

fn valid_range(len: usize) -> String {
    if len == 0 {
        "none (the axis is empty)".to_string()
    } else {
        format!("0..={}", len - 1)
    }
}

impl DataError {
    /// Shorthand for [`DataError::InvalidArgument`].
    pub fn invalid(name: &str, value: impl std::fmt::Display, allowed: &str) -> Self {
        DataError::InvalidArgument {
            name: name.to_string(),
            value: value.to_string(),
            allowed: allowed.to_string(),
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn format(path: &Path, msg: impl Into<String>) -> Self {
        DataError::Format {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
}

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A fresh temporary path in the same directory as `path`, hidden (leading dot) and unique
/// within this process and across processes (pid + counter). It keeps `path`'s extension at
/// the end, because some encoders (the PNG writer) choose the format from the extension.
pub(crate) fn temp_path_for(path: &Path) -> PathBuf {
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let name = format!(".{stem}.tmp-{}-{n}{ext}", std::process::id());
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.join(name),
        _ => PathBuf::from(name),
    }
}

/// Check that `path` names a file in an existing directory (clear error otherwise).
pub(crate) fn check_output_path(path: &Path) -> Result<(), DataError> {
    if path.file_name().is_none() {
        return Err(DataError::invalid(
            "path",
            format!("{:?}", path.display().to_string()),
            "a file name is required (the path ends in a directory)",
        ));
    }
    if path.is_dir() {
        return Err(DataError::invalid(
            "path",
            format!("{:?}", path.display().to_string()),
            "is a directory; give a file name",
        ));
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() && !dir.is_dir() {
            return Err(DataError::io(
                path,
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!("directory {} does not exist", dir.display()),
                ),
            ));
        }
    }
    Ok(())
}

/// Write a file atomically: `write` fills a temporary file next to `path` (it receives the
/// temporary path), then the temporary is flushed to disk and renamed over `path`.
/// On any error the temporary is removed and `path` is left untouched.
pub(crate) fn atomic_write<F>(path: &Path, write: F) -> Result<(), DataError>
where
    F: FnOnce(&Path) -> Result<(), DataError>,
{
    check_output_path(path)?;
    let tmp = temp_path_for(path);
    let result = write(&tmp).and_then(|()| {
        sync_file(&tmp)?;
        std::fs::rename(&tmp, path).map_err(|e| DataError::io(path, e))
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    } else {
        sync_parent_dir(path);
    }
    result
}

/// Flush a finished file's contents to disk.
pub(crate) fn sync_file(path: &Path) -> Result<(), DataError> {
    File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| DataError::io(path, e))
}

/// Best effort: make a rename durable by syncing the directory (not possible everywhere).
pub(crate) fn sync_parent_dir(path: &Path) {
    if let Some(dir) = path.parent() {
        let dir = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
}

/// Shortest text that reads back to exactly the same `f64` (`nan`, `inf`, `-inf` for the
/// non-finite values). Plain decimal for moderate magnitudes, exponent form otherwise.
pub fn format_f64_exact(v: f64) -> String {
    if v.is_nan() {
        "nan".to_string()
    } else if v.is_infinite() {
        if v > 0.0 {
            "inf".to_string()
        } else {
            "-inf".to_string()
        }
    } else {
        let a = v.abs();
        if a == 0.0 || (1e-4..1e15).contains(&a) {
            format!("{v}")
        } else {
            format!("{v:e}")
        }
    }
}

/// Parse numbers written by [`format_f64_exact`] (and the usual spellings of NaN/infinity).
pub fn parse_f64_lenient(s: &str) -> Option<f64> {
    let t = s.trim();
    match t.to_ascii_lowercase().as_str() {
        "nan" | "+nan" | "-nan" => Some(f64::NAN),
        "inf" | "+inf" | "infinity" | "+infinity" => Some(f64::INFINITY),
        "-inf" | "-infinity" => Some(f64::NEG_INFINITY),
        _ => t.parse::<f64>().ok(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_format_round_trips() {
        for v in [
            0.0,
            -0.0,
            1.0,
            0.1,
            1e-300,
            -2.5e-7,
            123456.789,
            1e20,
            f64::MIN_POSITIVE,
            f64::MAX,
        ] {
            let s = format_f64_exact(v);
            let back = parse_f64_lenient(&s).unwrap();
            assert_eq!(back.to_bits(), v.to_bits(), "{v} -> {s}");
        }
        assert_eq!(format_f64_exact(f64::NAN), "nan");
        assert_eq!(format_f64_exact(f64::NEG_INFINITY), "-inf");
        assert_eq!(format_f64_exact(-0.0), "-0");
        assert_eq!(format_f64_exact(1e-7), "1e-7");
    }

    #[test]
    fn index_error_names_index_and_range() {
        let e = DataError::IndexOutOfRange {
            what: "row",
            index: 70,
            len: 64,
        };
        assert_eq!(
            e.to_string(),
            "row index 70 is out of range: valid indices are 0..=63"
        );
    }

    #[test]
    fn temp_paths_are_unique_and_keep_extension() {
        let a = temp_path_for(Path::new("/tmp/x/fig.png"));
        let b = temp_path_for(Path::new("/tmp/x/fig.png"));
        assert_ne!(a, b);
        assert_eq!(a.extension().unwrap(), "png");
        assert_eq!(a.parent().unwrap(), Path::new("/tmp/x"));
    }
}
