//! Provenance embedded in files written from scripts (issue: protocols' files carry the protocol
//! name, its arguments, the script hash and the git revision): a PNG `tEXt` chunk with keyword
//! `bfpscope-provenance`, an XML comment at the end of an SVG, a trailing `# bfpscope provenance:`
//! line in CSV (numpy.loadtxt and our reader skip `#` lines; pandas needs `comment="#"`), a
//! `provenance` key in template JSON. Scans carry it in their metadata (`meta.protocol`,
//! `meta.script`, `meta.git_revision`).

use std::path::Path;

/// PNG keyword of the provenance text chunk.
pub const PNG_KEYWORD: &str = "bfpscope-provenance";

/// Insert a `tEXt` chunk (`keyword`, Latin-1 text) right after the IHDR chunk of a PNG file.
/// Characters outside Latin-1 are written as JSON escapes `\uXXXX` (UTF-16 units): valid in
/// the JSON strings they occur in, so the chunk's text stays parseable JSON.
pub fn png_add_text(path: &Path, keyword: &str, text: &str) -> Result<(), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    replace(path, png_with_text(path, &bytes, keyword, text)?)
}

/// Replace `path`'s contents atomically (temporary file, fsync, rename): a reader, or a crash,
/// sees the finished file before or after the stamp, never a torn one.
fn replace(path: &Path, bytes: Vec<u8>) -> Result<(), String> {
    super::atomic_write(path, |tmp| {
        std::fs::write(tmp, &bytes).map_err(|e| super::DataError::io(tmp, e))
    })
    .map_err(|e| e.to_string())
}

/// The bytes of PNG `bytes` (read from `path`) with a `tEXt` chunk inserted after IHDR.
fn png_with_text(path: &Path, bytes: &[u8], keyword: &str, text: &str) -> Result<Vec<u8>, String> {
    const SIG: &[u8] = b"\x89PNG\r\n\x1a\n";
    if bytes.len() < 33 || &bytes[..8] != SIG || &bytes[12..16] != b"IHDR" {
        return Err(format!("{}: not a PNG file", path.display()));
    }
    let ihdr_len = u32::from_be_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
    let after_ihdr = 8 + 12 + ihdr_len;
    let mut data: Vec<u8> = keyword.bytes().collect();
    data.push(0);
    for ch in text.chars() {
        if (ch as u32) < 256 && ch != '\0' {
            data.push(ch as u32 as u8);
        } else {
            let mut buf = [0u16; 2];
            for unit in ch.encode_utf16(&mut buf) {
                data.extend(format!("\\u{:04x}", unit).bytes());
            }
        }
    }
    let mut chunk = Vec::with_capacity(data.len() + 12);
    chunk.extend((data.len() as u32).to_be_bytes());
    let mut crc = crc32fast::Hasher::new();
    crc.update(b"tEXt");
    crc.update(&data);
    chunk.extend(b"tEXt");
    chunk.extend(&data);
    chunk.extend(crc.finalize().to_be_bytes());
    let mut out = Vec::with_capacity(bytes.len() + chunk.len());
    out.extend(&bytes[..after_ihdr]);
    out.extend(&chunk);
    out.extend(&bytes[after_ihdr..]);
    Ok(out)
}

/// Read the text of the first `tEXt` chunk with `keyword` (None when absent).
pub fn png_text(path: &Path, keyword: &str) -> Option<String> {
    let bytes = std::fs::read(path).ok()?;
    let mut i = 8;
    while i + 12 <= bytes.len() {
        let len = u32::from_be_bytes(bytes[i..i + 4].try_into().ok()?) as usize;
        let kind = &bytes[i + 4..i + 8];
        let data = bytes.get(i + 8..i + 8 + len)?;
        if kind == b"tEXt" {
            if let Some(z) = data.iter().position(|&b| b == 0) {
                if &data[..z] == keyword.as_bytes() {
                    return Some(data[z + 1..].iter().map(|&b| b as char).collect());
                }
            }
        }
        i += 12 + len;
    }
    None
}

/// Embed provenance JSON in a figure (.png: text chunk; .svg: trailing XML comment) or a CSV
/// file (trailing `#` line), chosen by the extension. Other files are left alone. The stamped
/// file replaces the unstamped one atomically (never rewritten in place).
pub fn embed(path: &Path, json: &str) -> Result<(), String> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let append = |line: String| -> Result<(), String> {
        let mut bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
        bytes.extend(line.as_bytes());
        replace(path, bytes)
    };
    match ext.as_str() {
        "png" => png_add_text(path, PNG_KEYWORD, json),
        "svg" => append(format!(
            "\n<!-- bfpscope provenance: {} -->\n",
            json.replace("--", "- -")
        )),
        "csv" => append(format!("# bfpscope provenance: {json}\n")),
        _ => Ok(()),
    }
}
