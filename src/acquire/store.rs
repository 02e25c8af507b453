//! Where scans go: the session folder with increasing scan numbers, written to a temporary
//! name and renamed (hard-linked, so an existing file is never overwritten).
//!
//! Interim format: JSON (`scan_0001.json`, the whole `Scan` with metadata). The data branch's
//! `data::npz::save_scan` / `data::session::autosave` replace `write_scan` / `load_scan` here.

use crate::data::Scan;
use std::io::Write;
use std::path::{Path, PathBuf};

/// File extension of autosaved scans.
pub const SCAN_EXT: &str = "json";

/// The session folder.
#[derive(Debug, Clone)]
pub struct SessionStore {
    dir: PathBuf,
}

impl SessionStore {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Highest scan number present in the folder (0 when none).
    pub fn last_number(&self) -> u32 {
        let Ok(rd) = std::fs::read_dir(&self.dir) else {
            return 0;
        };
        rd.filter_map(|e| e.ok())
            .filter_map(|e| parse_number(&e.file_name().to_string_lossy()))
            .max()
            .unwrap_or(0)
    }

    /// The path the next scan would get (`DIR/scan_0007.json`).
    pub fn next_scan_path(&self) -> PathBuf {
        self.dir.join(scan_file_name(self.last_number() + 1))
    }

    /// Save `scan` under the next free number; never overwrites an existing file.
    pub fn autosave(&self, scan: &Scan) -> std::io::Result<PathBuf> {
        std::fs::create_dir_all(&self.dir)?;
        let mut n = self.last_number() + 1;
        let tmp = self.dir.join(format!(
            ".scan_tmp_{}_{}.{SCAN_EXT}",
            std::process::id(),
            unique()
        ));
        write_file(&tmp, scan)?;
        loop {
            let dest = self.dir.join(scan_file_name(n));
            // hard_link fails if `dest` exists: a concurrent writer can never be overwritten.
            match std::fs::hard_link(&tmp, &dest) {
                Ok(()) => {
                    let _ = std::fs::remove_file(&tmp);
                    return Ok(dest);
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => n += 1,
                Err(e) => {
                    let _ = std::fs::remove_file(&tmp);
                    return Err(e);
                }
            }
        }
    }
}

fn unique() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static N: AtomicU64 = AtomicU64::new(0);
    N.fetch_add(1, Ordering::Relaxed)
}

/// `scan_0042.json`.
pub fn scan_file_name(n: u32) -> String {
    format!("scan_{n:04}.{SCAN_EXT}")
}

fn parse_number(name: &str) -> Option<u32> {
    let rest = name.strip_prefix("scan_")?;
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    if digits.is_empty() || !rest[digits.len()..].starts_with('.') {
        return None;
    }
    digits.parse().ok()
}

fn write_file(path: &Path, scan: &Scan) -> std::io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    let text = serde_json::to_vec(scan).map_err(std::io::Error::other)?;
    f.write_all(&text)?;
    f.sync_all()
}

/// Save a scan to `path` (temporary name + rename). Refuses to overwrite an existing file.
pub fn save_scan(path: &Path, scan: &Scan) -> std::io::Result<()> {
    if path.exists() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            format!("{} exists; scans are never overwritten", path.display()),
        ));
    }
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d)?;
    }
    let tmp = path.with_extension(format!("tmp{}", unique()));
    write_file(&tmp, scan)?;
    let r = std::fs::hard_link(&tmp, path);
    let _ = std::fs::remove_file(&tmp);
    r
}

/// Load a scan written by [`save_scan`] / [`SessionStore::autosave`]. JSON `null` pixels
/// (unmeasured points of a partial scan; JSON has no NaN) come back as NaN.
pub fn load_scan(path: &Path) -> std::io::Result<Scan> {
    let bad = |what: &str| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{}: {what}", path.display()),
        )
    };
    let text = std::fs::read(path)?;
    let v: serde_json::Value = serde_json::from_slice(&text).map_err(|e| bad(&e.to_string()))?;
    let nums = |a: &serde_json::Value| -> Option<Vec<f64>> {
        a.as_array()?
            .iter()
            .map(|x| {
                if x.is_null() {
                    Some(f64::NAN)
                } else {
                    x.as_f64()
                }
            })
            .collect()
    };
    let image = |ch: &str| -> std::io::Result<crate::data::Image> {
        let c = v.get(ch).ok_or_else(|| bad(&format!("no channel {ch}")))?;
        let d = c.get("data").ok_or_else(|| bad("no data"))?;
        let dim = nums(&d["dim"])
            .filter(|d| d.len() == 2)
            .ok_or_else(|| bad("bad dim"))?;
        let data = nums(&d["data"]).ok_or_else(|| bad("bad pixel data"))?;
        let x = nums(&c["x"]).ok_or_else(|| bad("bad x axis"))?;
        let y = nums(&c["y"]).ok_or_else(|| bad("bad y axis"))?;
        let (r, cc) = (dim[0] as usize, dim[1] as usize);
        if data.len() != r * cc || x.len() != cc || y.len() != r {
            return Err(bad("array sizes do not match"));
        }
        let arr =
            ndarray::Array2::from_shape_vec((r, cc), data).map_err(|e| bad(&e.to_string()))?;
        Ok(crate::data::Image::new(arr, x, y).with_axis_names(
            c["x_name"].as_str().unwrap_or("x"),
            c["y_name"].as_str().unwrap_or("y"),
        ))
    };
    Ok(Scan {
        sx: image("sx")?,
        sy: image("sy")?,
        sz: image("sz")?,
        status: serde_json::from_value(v["status"].clone()).map_err(|e| bad(&e.to_string()))?,
        meta: v["meta"].clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn numbers_parse() {
        assert_eq!(parse_number("scan_0012.json"), Some(12));
        assert_eq!(parse_number("scan_12345.npz"), Some(12345));
        assert_eq!(parse_number("scan_x.json"), None);
        assert_eq!(parse_number(".scan_tmp_1_2.json"), None);
    }
}
