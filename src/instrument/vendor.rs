//! Vendor C libraries loaded at run time (`libloading`: `dlopen` / `LoadLibrary`), so the binary
//! builds, tests and runs on a machine without them: Mad City Labs' Madlib
//! (`madlib/`) and NI-DAQmx (`nidaqmx/`).
//!
//! Where a library is looked for, in order: the path the config names (`[stage] library`,
//! `[qpd] library`; then only that path is tried), an environment variable
//! (`BFPSCOPE_MADLIB`, `BFPSCOPE_NIDAQMX`), the library's bare file name (the dynamic loader's
//! own search: `LD_LIBRARY_PATH`, `/etc/ld.so.cache`; on Windows the DLL search path), then the
//! vendors' usual install folders. A library that is not found is an error naming the library,
//! every place searched and how to point at it.

use super::DeviceError;
use std::path::{Path, PathBuf};

/// Where one vendor library is looked for.
#[derive(Debug, Clone, Copy)]
pub struct LibrarySpec {
    /// What it is, for messages (`"Mad City Labs Madlib"`).
    pub what: &'static str,
    /// The config key that names it (`"stage.library"`).
    pub config_key: &'static str,
    /// The environment variable that names it.
    pub env_var: &'static str,
    /// File names handed to the dynamic loader as they are (its own search path).
    pub names: &'static [&'static str],
    /// Full paths tried after the names.
    pub paths: &'static [&'static str],
}

/// The places `spec` is looked for, in order: `configured` alone when set; else the
/// environment variable's value (when set and not empty), the bare names, the usual paths.
pub fn candidates(
    spec: &LibrarySpec,
    configured: Option<&Path>,
    env_value: Option<&str>,
) -> Vec<PathBuf> {
    if let Some(p) = configured {
        return vec![p.to_path_buf()];
    }
    let mut v = Vec::new();
    if let Some(e) = env_value.map(str::trim).filter(|e| !e.is_empty()) {
        v.push(PathBuf::from(e));
    }
    v.extend(spec.names.iter().map(PathBuf::from));
    v.extend(spec.paths.iter().map(PathBuf::from));
    v
}

/// The message for a library found nowhere: which library, where it was searched (each place
/// with the loader's reason) and how to point at it.
pub fn not_found_message(
    spec: &LibrarySpec,
    configured: Option<&Path>,
    tried: &[(PathBuf, String)],
) -> String {
    let places = tried
        .iter()
        .map(|(p, why)| format!("  {}: {why}", p.display()))
        .collect::<Vec<_>>()
        .join("\n");
    let how = match configured {
        Some(_) => format!(
            "check `{}` in bfpscope.toml (the vendor's library must be installed at that path)",
            spec.config_key
        ),
        None => format!(
            "install the vendor's library, or point at it with `{} = \"/path/to/{}\"` in bfpscope.toml or the \
             environment variable {}",
            spec.config_key,
            spec.names.first().copied().unwrap_or("library"),
            spec.env_var
        ),
    };
    format!(
        "{} library not loaded; searched:\n{places}\n{how}",
        spec.what
    )
}

/// Load the first of the candidates that opens. `device` names the device for the error.
pub fn open(
    spec: &LibrarySpec,
    configured: Option<&Path>,
    device: &str,
) -> Result<(libloading::Library, PathBuf), DeviceError> {
    let env = std::env::var(spec.env_var).ok();
    let mut tried = Vec::new();
    for p in candidates(spec, configured, env.as_deref()) {
        // SAFETY: loading a shared library runs its initialisers; these are the vendors'
        // libraries (or the project's fake), named by the user's config or the usual paths.
        match unsafe { libloading::Library::new(&p) } {
            Ok(lib) => return Ok((lib, p)),
            Err(e) => tried.push((p, loader_reason(&e))),
        }
    }
    Err(DeviceError::Other {
        device: device.to_string(),
        detail: not_found_message(spec, configured, &tried),
    })
}

/// The loader's reason, without libloading's own wording around it.
fn loader_reason(e: &libloading::Error) -> String {
    let s = e.to_string();
    // "dlopen failed: libx.so: cannot open shared object file: No such file or directory"
    s.rsplit_once(": ")
        .map(|(_, r)| r.to_string())
        .filter(|r| !r.is_empty())
        .unwrap_or(s)
}

/// Copy the function pointer `name` out of `lib` (the caller keeps `lib` alive as long as the
/// pointer is used). A missing symbol is an error naming the library and the function.
///
/// # Safety
/// `T` must be the function's exact type as declared by the vendor's header.
pub unsafe fn symbol<T: Copy>(
    lib: &libloading::Library,
    path: &Path,
    name: &str,
    device: &str,
) -> Result<T, DeviceError> {
    let mut z = name.as_bytes().to_vec();
    z.push(0);
    match unsafe { lib.get::<T>(&z) } {
        Ok(s) => Ok(*s),
        Err(_) => Err(DeviceError::Other {
            device: device.to_string(),
            detail: format!(
                "{} has no function `{name}`: not the vendor's library, or a version without it",
                path.display()
            ),
        }),
    }
}

/// As [`symbol`], `None` when the library does not export it (optional functions).
///
/// # Safety
/// As [`symbol`].
pub unsafe fn optional_symbol<T: Copy>(lib: &libloading::Library, name: &str) -> Option<T> {
    let mut z = name.as_bytes().to_vec();
    z.push(0);
    unsafe { lib.get::<T>(&z) }.ok().map(|s| *s)
}

/// Declares a vendor library's function table and its loader, one row a C function:
/// `field: Type = "Symbol",`, under `required` the functions the library must export (a missing
/// one is an error naming it, as [`symbol`] says), under `optional` the ones it may lack
/// (`Option<Type>`, `None` when it does not export them). The struct keeps the library open
/// (`_lib`) as long as the pointers live, and the `path` it was loaded from; `load` looks for
/// the library as `$spec` says (see [`open`]).
///
/// ```ignore
/// vendor_library! {
///     /// The loaded library and its functions.
///     pub struct Madlib from SPEC {
///         required {
///             release_handle: ReleaseHandle = "MCL_ReleaseHandle",
///         }
///         optional {
///             init_library: InitLibrary = "MCL_InitLibrary",
///         }
///     }
/// }
/// ```
macro_rules! vendor_library {
    (
        $(#[$meta:meta])*
        pub struct $name:ident from $spec:ident {
            required {
                $($req:ident: $rty:ty = $rsym:literal,)*
            }
            optional {
                $($opt:ident: $oty:ty = $osym:literal,)*
            }
        }
    ) => {
        $(#[$meta])*
        pub struct $name {
            _lib: libloading::Library,
            pub path: std::path::PathBuf,
            $(pub $req: $rty,)*
            $(pub $opt: Option<$oty>,)*
        }

        impl $name {
            /// Load the library from `configured` or the usual places (see `vendor`) and look
            /// up its functions, the required ones first, in the order declared.
            pub fn load(
                configured: Option<&std::path::Path>,
                device: &str,
            ) -> Result<$name, $crate::instrument::DeviceError> {
                use $crate::instrument::vendor::{open, optional_symbol, symbol};
                let (lib, path) = open(&$spec, configured, device)?;
                // SAFETY: each row's type is the vendor header's declaration of its symbol.
                unsafe {
                    Ok($name {
                        $($req: symbol(&lib, &path, $rsym, device)?,)*
                        $($opt: optional_symbol(&lib, $osym),)*
                        _lib: lib,
                        path,
                    })
                }
            }
        }
    };
}
pub(crate) use vendor_library;

/// A NUL-terminated copy of `s` for a C `const char[]` argument; an interior NUL is an error
/// naming the argument.
pub fn c_string(device: &str, what: &str, s: &str) -> Result<std::ffi::CString, DeviceError> {
    std::ffi::CString::new(s).map_err(|_| DeviceError::Other {
        device: device.to_string(),
        detail: format!("{what} {s:?} contains a NUL character"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEC: LibrarySpec = LibrarySpec {
        what: "Test vendor",
        config_key: "stage.library",
        env_var: "BFPSCOPE_TEST_VENDOR",
        names: &["libtestvendor.so"],
        paths: &["/usr/local/lib/libtestvendor.so"],
    };

    #[test]
    fn a_configured_path_is_the_only_one_tried() {
        let c = candidates(&SPEC, Some(Path::new("/opt/x/lib.so")), Some("/env/lib.so"));
        assert_eq!(c, vec![PathBuf::from("/opt/x/lib.so")]);
    }

    #[test]
    fn without_config_the_env_var_then_names_then_paths() {
        let c = candidates(&SPEC, None, Some(" /env/lib.so "));
        assert_eq!(
            c,
            vec![
                PathBuf::from("/env/lib.so"),
                PathBuf::from("libtestvendor.so"),
                PathBuf::from("/usr/local/lib/libtestvendor.so")
            ]
        );
        assert_eq!(candidates(&SPEC, None, Some("")).len(), 2);
    }

    #[test]
    fn a_missing_library_says_what_where_and_how() {
        let e = open(
            &SPEC,
            Some(Path::new("/nonexistent/libtestvendor.so")),
            "Test stage",
        )
        .map(|_| ())
        .unwrap_err();
        let m = e.to_string();
        assert!(
            m.starts_with("Test stage: Test vendor library not loaded"),
            "{m}"
        );
        assert!(m.contains("/nonexistent/libtestvendor.so: "), "{m}");
        assert!(m.contains("check `stage.library`"), "{m}");
        let m = not_found_message(
            &SPEC,
            None,
            &[(PathBuf::from("libtestvendor.so"), "no".into())],
        );
        assert!(
            m.contains("`stage.library = \"/path/to/libtestvendor.so\"`")
                && m.contains("BFPSCOPE_TEST_VENDOR"),
            "{m}"
        );
    }
}
