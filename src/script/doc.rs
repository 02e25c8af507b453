//! A binding's declaration ([`Doc`]: name, family, arguments with units, summary, help,
//! examples) and the error type every binding returns ([`RResult`], [`fail`]). A leaf: the
//! context keeps the declarations for `help`, the registry (which re-exports these) turns them
//! into Rhai registrations, pages and tests. See `registry.rs` for how a family declares one.

use rhai::EvalAltResult;
use std::sync::Arc;

/// Result type of every binding.
pub type RResult<T> = Result<T, Box<EvalAltResult>>;

/// A script error with `msg` (the binding names itself in the message).
pub fn fail<T>(msg: impl Into<String>) -> RResult<T> {
    Err(msg.into().into())
}

/// One key of a binding's map argument, declared once: a `const` of the family file names the
/// key, its type and unit (`const DWELL: Opt = Opt::new("dwell", "float", "s");`). The
/// declaration (`Doc::map(…, &[DWELL.doc("optional: …")])`) and every read
/// (`o.f64_or(DWELL, …)`) use that constant, so the key's string is written once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Opt {
    pub name: &'static str,
    pub ty: &'static str,
    pub unit: &'static str,
}

impl Opt {
    pub const fn new(name: &'static str, ty: &'static str, unit: &'static str) -> Opt {
        Opt { name, ty, unit }
    }
    /// The same key as another binding of the family takes it, with another type or unit
    /// (`x` a position here, an `[x0, x1]` region there).
    pub const fn typed(self, ty: &'static str, unit: &'static str) -> Opt {
        Opt {
            name: self.name,
            ty,
            unit,
        }
    }
    /// The key as [`Doc::map`] declares it, with its help (a help starting with `"optional"`
    /// or containing `"default"` marks the key optional).
    pub const fn doc<D>(self, help: D) -> (&'static str, &'static str, &'static str, D) {
        (self.name, self.ty, self.unit, help)
    }
}

/// A map key as [`Opts`](super::registry::Opts) reads it: a declared [`Opt`] (or, for a key
/// built at run time, its name).
pub trait Key {
    fn key(&self) -> &str;
}

impl Key for Opt {
    fn key(&self) -> &str {
        self.name
    }
}

impl Key for str {
    fn key(&self) -> &str {
        self
    }
}

impl Key for String {
    fn key(&self) -> &str {
        self
    }
}

impl<K: Key + ?Sized> Key for &K {
    fn key(&self) -> &str {
        (**self).key()
    }
}

/// One argument (or one key of a map argument).
#[derive(Debug, Clone, PartialEq)]
pub struct Param {
    pub name: String,
    /// `float`, `int`, `string`, `bool`, `map`, `array`, `Scan`, `Image`, `fn`, `number`
    /// (int or float), `[from, to]`...
    pub ty: String,
    /// Unit at the script boundary (`µm`, `s`, `nm`, ...; empty when dimensionless).
    pub unit: String,
    pub doc: String,
    pub optional: bool,
    /// Keys of a map argument.
    pub keys: Vec<Param>,
}

/// What a binding is in Rhai.
#[derive(Debug, Clone, PartialEq)]
pub enum Kind {
    Function,
    /// `value.name(args)`: the first Rhai argument is the value of type `ty`.
    Method {
        ty: String,
    },
    /// `value.name`: a property getter of type `ty`.
    Property {
        ty: String,
    },
    /// Operators (`img * 2.0`), documented once, registered by hand.
    Operator {
        ty: String,
    },
}

/// An example and its expected result: a Rhai expression compared by value (floats to a
/// relative 1e-9), or `error: <text>` meaning the code must fail with a message containing
/// `<text>`.
#[derive(Debug, Clone, PartialEq)]
pub struct Example {
    pub code: String,
    pub expect: String,
}

/// The single declaration of a binding.
#[derive(Debug, Clone, PartialEq)]
pub struct Doc {
    pub name: String,
    pub family: String,
    pub kind: Kind,
    pub params: Vec<Param>,
    /// (type, description incl. units)
    pub returns: (String, String),
    pub summary: String,
    pub help: String,
    pub examples: Vec<Example>,
    /// Extra call forms (overloads), e.g. `help(name)`. The first form comes from `params`.
    pub forms: Vec<String>,
}

/// What a binding's body needs from its declaration to check its arguments: its name, the
/// allowed map keys and its usage line.
#[derive(Debug, Clone)]
pub struct Spec {
    pub name: String,
    pub keys: Vec<String>,
    pub usage: String,
}

impl Doc {
    pub(super) fn new(name: &str, family: &str, kind: Kind) -> Doc {
        Doc {
            name: name.into(),
            family: family.into(),
            kind,
            params: vec![],
            returns: ("()".into(), String::new()),
            summary: String::new(),
            help: String::new(),
            examples: vec![],
            forms: vec![],
        }
    }
    /// A free function `name(args)`; its family is the file that declares it.
    pub fn func(name: &str) -> Doc {
        Doc::new(name, "", Kind::Function)
    }
    /// A method `value.name(args)` of the Rhai type `ty`; its family, too, is the file that
    /// declares it (not the type).
    pub fn method(ty: &str, name: &str) -> Doc {
        Doc::new(name, "", Kind::Method { ty: ty.into() })
    }
    /// A property `value.name` of the Rhai type `ty`.
    pub fn property(ty: &str, name: &str) -> Doc {
        Doc::new(name, "", Kind::Property { ty: ty.into() })
    }
    /// Operators of the type `ty`, documented under `name` (e.g. `arithmetic`).
    pub fn operator(ty: &str, name: &str) -> Doc {
        Doc::new(name, "", Kind::Operator { ty: ty.into() })
    }
    /// A required argument.
    pub fn arg(mut self, name: &str, ty: &str, unit: &str, doc: &str) -> Doc {
        self.params.push(Param {
            name: name.into(),
            ty: ty.into(),
            unit: unit.into(),
            doc: doc.into(),
            optional: false,
            keys: vec![],
        });
        self
    }
    /// A required argument declared once for the bindings that share it, as
    /// `(name, type, unit, doc)` (`TEMPLATE_ARG`).
    pub fn arg_of(self, (name, ty, unit, doc): (&str, &str, &str, &str)) -> Doc {
        self.arg(name, ty, unit, doc)
    }
    /// An optional argument (an overload without it exists).
    pub fn opt(mut self, name: &str, ty: &str, unit: &str, doc: &str) -> Doc {
        self.params.push(Param {
            name: name.into(),
            ty: ty.into(),
            unit: unit.into(),
            doc: doc.into(),
            optional: true,
            keys: vec![],
        });
        self
    }
    /// A map argument with its keys `(name, type, unit, doc)`; a doc starting with
    /// `"optional"` or containing `"default"` marks the key optional.
    pub fn map<D: AsRef<str>>(
        mut self,
        name: &str,
        doc: &str,
        keys: &[(&str, &str, &str, D)],
    ) -> Doc {
        let keys = keys
            .iter()
            .map(|(n, t, u, d)| Param {
                name: (*n).into(),
                ty: (*t).into(),
                unit: (*u).into(),
                doc: d.as_ref().into(),
                optional: d.as_ref().starts_with("optional") || d.as_ref().contains("default"),
                keys: vec![],
            })
            .collect();
        self.params.push(Param {
            name: name.into(),
            ty: "map".into(),
            unit: String::new(),
            doc: doc.into(),
            // "optional …": a form without the map exists
            optional: doc.starts_with("optional"),
            keys,
        });
        self
    }
    /// The optional options map `opts`, the last argument (a form without it exists), with
    /// its keys as [`Doc::map`] takes them.
    pub fn opts<D: AsRef<str>>(self, keys: &[(&str, &str, &str, D)]) -> Doc {
        self.map("opts", "optional", keys)
    }
    pub fn returns(mut self, ty: &str, doc: &str) -> Doc {
        self.returns = (ty.into(), doc.into());
        self
    }
    pub fn summary(mut self, s: &str) -> Doc {
        self.summary = s.into();
        self
    }
    pub fn help(mut self, s: &str) -> Doc {
        self.help = s.into();
        self
    }
    pub fn example(mut self, code: &str, expect: &str) -> Doc {
        self.examples.push(Example {
            code: code.into(),
            expect: expect.into(),
        });
        self
    }
    /// Another call form shown in the usage (an overload).
    pub fn form(mut self, sig: &str) -> Doc {
        self.forms.push(sig.into());
        self
    }

    /// The receiver placeholder for methods/properties: `scan`, `img`, `profile`.
    pub(super) fn receiver(ty: &str) -> String {
        match ty {
            "Image" => "img".into(),
            other => other.to_ascii_lowercase(),
        }
    }

    /// The main call form: `scan_xy(#{x, y, nx, ny, z, dwell, rel, snake})`, `img.row(i)`,
    /// `scan.sx`.
    pub fn signature(&self) -> String {
        let args = self
            .params
            .iter()
            .map(|p| {
                let s = if p.keys.is_empty() {
                    p.name.clone()
                } else {
                    format!(
                        "#{{{}}}",
                        p.keys
                            .iter()
                            .map(|k| k.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                };
                if p.optional {
                    format!("[{s}]")
                } else {
                    s
                }
            })
            .collect::<Vec<_>>()
            .join(", ");
        match &self.kind {
            Kind::Function => format!("{}({args})", self.name),
            Kind::Method { ty } => format!("{}.{}({args})", Self::receiver(ty), self.name),
            Kind::Property { ty } => format!("{}.{}", Self::receiver(ty), self.name),
            Kind::Operator { .. } => self
                .forms
                .first()
                .cloned()
                .unwrap_or_else(|| self.name.clone()),
        }
    }

    /// All call forms, one per line.
    pub fn usage(&self) -> String {
        let mut v = vec![self.signature()];
        let skip = matches!(self.kind, Kind::Operator { .. }) as usize;
        v.extend(self.forms.iter().skip(skip).cloned());
        v.join("  |  ")
    }

    /// Units of all arguments and keys, grouped: `x, y, z: µm; dwell: s`.
    pub fn units(&self) -> String {
        let mut groups: Vec<(String, Vec<String>)> = vec![];
        let mut add = |unit: &str, name: &str| {
            if unit.is_empty() {
                return;
            }
            if let Some(g) = groups.iter_mut().find(|g| g.0 == unit) {
                if !g.1.iter().any(|n| n == name) {
                    g.1.push(name.into());
                }
            } else {
                groups.push((unit.into(), vec![name.into()]));
            }
        };
        for p in &self.params {
            add(&p.unit, &p.name);
            for k in &p.keys {
                add(&k.unit, &k.name);
            }
        }
        groups
            .iter()
            .map(|(u, n)| format!("{}: {u}", n.join(", ")))
            .collect::<Vec<_>>()
            .join("; ")
    }

    /// One line for `help()`: signature, summary, units.
    pub fn one_line(&self) -> String {
        let u = self.units();
        let units = if u.is_empty() {
            String::new()
        } else {
            format!("  [{u}]")
        };
        let sig = self.signature();
        if sig.chars().count() > 34 {
            format!("{sig}\n      {:<30} {}{units}", "", self.summary)
        } else {
            format!("{sig:<34} {}{units}", self.summary)
        }
    }

    /// The long help for `help("name")`.
    pub fn long_help(&self) -> String {
        let mut s = format!("{}  —  {}\n", self.usage(), self.summary);
        s.push_str(&format!(
            "family: {} (src/script/{}.rs)\n",
            self.family, self.family
        ));
        let mut args = vec![];
        for p in &self.params {
            args.push(param_line(p, "  "));
            for k in &p.keys {
                args.push(param_line(k, "      "));
            }
        }
        if !args.is_empty() {
            s.push_str("arguments:\n");
            s.push_str(&args.join("\n"));
            s.push('\n');
        }
        if self.returns.0 != "()" || !self.returns.1.is_empty() {
            s.push_str(
                &format!("returns: {} {}\n", self.returns.0, self.returns.1).replace(" \n", "\n"),
            );
        }
        if !self.help.is_empty() {
            s.push('\n');
            s.push_str(self.help.trim());
            s.push('\n');
        }
        if !self.examples.is_empty() {
            s.push_str("\nexamples:\n");
            for e in &self.examples {
                s.push_str(&format!("  {}\n    → {}\n", e.code, e.expect));
            }
        }
        s
    }

    /// The argument-checking view of this declaration.
    pub fn spec(&self) -> Arc<Spec> {
        Arc::new(Spec {
            name: self.name.clone(),
            keys: self
                .params
                .iter()
                .flat_map(|p| p.keys.iter().map(|k| k.name.clone()))
                .collect(),
            usage: self.usage(),
        })
    }
}

fn param_line(p: &Param, indent: &str) -> String {
    let unit = if p.unit.is_empty() {
        String::new()
    } else {
        format!(" [{}]", p.unit)
    };
    let opt = if p.optional && !p.doc.starts_with("optional") {
        " (optional)"
    } else {
        ""
    };
    format!("{indent}{:<10} {}{unit}{opt}  {}", p.name, p.ty, p.doc)
}
