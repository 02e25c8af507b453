//! CSV for profiles and tables: one header line, comma-separated, one row per sample,
//! numbers in the shortest form that reads back to the same `f64` (`nan`, `inf`, `-inf` for
//! the non-finite values). Readable with `numpy.genfromtxt(path, delimiter=",", names=True)`,
//! `pandas.read_csv(path, comment="#")` (files written from scripts end with a `#` provenance line), spreadsheets. Lines starting with `#` are ignored when reading.

use super::{atomic_write, format_f64_exact, parse_f64_lenient, DataError, Profile};
use std::io::Write;
use std::path::Path;

/// Header of a profile's position column: `<t_name>_um`.
pub fn profile_position_header(p: &Profile) -> String {
    format!("{}_um", p.t_name)
}

/// Save a profile as two columns: `<t_name>_um,value`.
pub fn save_csv_profile(path: impl AsRef<Path>, profile: &Profile) -> Result<(), DataError> {
    if profile.t.len() != profile.v.len() {
        return Err(DataError::invalid(
            "profile",
            format!("{} positions, {} values", profile.t.len(), profile.v.len()),
            "positions and values must have the same length",
        ));
    }
    let headers = [profile_position_header(profile), "value".to_string()];
    save_csv_table(path, &headers, &[&profile.t[..], &profile.v[..]])
}

/// Load a profile saved by [`save_csv_profile`] (any two-column CSV with a header works; the
/// first header minus a `_um` suffix becomes `t_name`).
pub fn load_csv_profile(path: impl AsRef<Path>) -> Result<Profile, DataError> {
    let path = path.as_ref();
    let (headers, mut cols) = load_csv_table(path)?;
    if cols.len() != 2 {
        return Err(DataError::format(
            path,
            format!(
                "a profile CSV has 2 columns (position, value); found {}",
                cols.len()
            ),
        ));
    }
    let v = cols.pop().unwrap_or_default();
    let t = cols.pop().unwrap_or_default();
    let name = headers[0].strip_suffix("_um").unwrap_or(&headers[0]);
    Ok(Profile {
        t,
        v,
        t_name: name.to_string(),
    })
}

/// Save a table: `headers[k]` names column `columns[k]`; all columns must have the same length.
pub fn save_csv_table<H, C>(
    path: impl AsRef<Path>,
    headers: &[H],
    columns: &[C],
) -> Result<(), DataError>
where
    H: AsRef<str>,
    C: AsRef<[f64]>,
{
    let path = path.as_ref();
    if headers.is_empty() {
        return Err(DataError::invalid(
            "headers",
            "[]",
            "a table needs at least one column",
        ));
    }
    if headers.len() != columns.len() {
        return Err(DataError::invalid(
            "headers",
            format!("{} names", headers.len()),
            &format!("one name per column ({} columns)", columns.len()),
        ));
    }
    let n = columns[0].as_ref().len();
    for (k, c) in columns.iter().enumerate() {
        if c.as_ref().len() != n {
            return Err(DataError::invalid(
                &format!("column {k} ({:?})", headers[k].as_ref()),
                format!("{} rows", c.as_ref().len()),
                &format!("all columns must have the same length as column 0 ({n} rows)"),
            ));
        }
    }
    let mut text = String::new();
    let head: Vec<String> = headers.iter().map(|h| quote(h.as_ref())).collect();
    text += &head.join(",");
    text.push('\n');
    for i in 0..n {
        for (k, c) in columns.iter().enumerate() {
            if k > 0 {
                text.push(',');
            }
            text += &format_f64_exact(c.as_ref()[i]);
        }
        text.push('\n');
    }
    atomic_write(path, |tmp| {
        let mut f = std::fs::File::create(tmp).map_err(|e| DataError::io(tmp, e))?;
        f.write_all(text.as_bytes())
            .map_err(|e| DataError::io(tmp, e))
    })
}

/// Load a CSV table: header names and the columns of numbers. Lines starting with `#` and
/// blank lines are skipped; every row must have one value per header.
pub fn load_csv_table(path: impl AsRef<Path>) -> Result<(Vec<String>, Vec<Vec<f64>>), DataError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((_, header_line)) = lines.next() else {
        return Err(DataError::format(
            path,
            "no header line (the file is empty)",
        ));
    };
    let headers = split_fields(header_line);
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); headers.len()];
    for (lineno, line) in lines {
        let fields = split_fields(line);
        if fields.len() != headers.len() {
            return Err(DataError::format(
                path,
                format!(
                    "line {}: {} fields, the header has {}",
                    lineno + 1,
                    fields.len(),
                    headers.len()
                ),
            ));
        }
        for (k, f) in fields.iter().enumerate() {
            let v = parse_f64_lenient(f).ok_or_else(|| {
                DataError::format(
                    path,
                    format!(
                        "line {}, column {:?}: {:?} is not a number",
                        lineno + 1,
                        headers[k],
                        f
                    ),
                )
            })?;
            cols[k].push(v);
        }
    }
    Ok((headers, cols))
}

/// Quote a header field if it contains a comma or quote (RFC 4180); line breaks become
/// spaces so that every record stays on one line.
fn quote(s: &str) -> String {
    let s = s.replace(['\n', '\r'], " ");
    if s.contains([',', '"']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s
    }
}

/// Split one CSV line into fields, honouring RFC 4180 quotes.
fn split_fields(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut in_quotes = false;
    let mut chars = line.trim_end_matches('\r').chars().peekable();
    while let Some(c) = chars.next() {
        match (c, in_quotes) {
            ('"', true) if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            ('"', _) => in_quotes = !in_quotes,
            (',', false) => out.push(std::mem::take(&mut cur)),
            (c, _) => cur.push(c),
        }
    }
    out.push(cur);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quoting_round_trips() {
        let h = ["a,b", "say \"hi\"", "plain"];
        let line: Vec<String> = h.iter().map(|s| quote(s)).collect();
        assert_eq!(split_fields(&line.join(",")), h);
    }
}
