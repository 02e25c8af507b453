//! The binding registry: every script binding is declared once — name, family, arguments with
//! types and units, one-line summary, help text, examples with expected results — and from
//! that one declaration come the Rhai registration, `help()` / `help("name")`, REPL completion
//! (names and map keys), `docs/api.md` and the test that runs every example.
//!
//! A family file (`src/script/<family>.rs`) has one `pub fn register(r: &mut Registrar)`:
//!
//! ```ignore
//! pub fn register(r: &mut Registrar) {
//!     let ctx = r.ctx();
//!     let d = Doc::func("p_scat_ratio")
//!         .arg("d_nm", "float", "nm", "particle diameter")
//!         .arg("n", "float", "", "refractive index of the particle")
//!         .returns("float", "scattered / incident power")
//!         .summary("fraction of the beam power a small sphere scatters")
//!         .help("Rayleigh limit, suppl. S3, eq. (S12).")
//!         .example("p_scat_ratio(110, 1.572) > 0.0", "true");
//!     r.bind(d, |d_nm: Dynamic, n: Dynamic| p_scat_ratio(&d_nm, &n));
//! }
//!
//! /// `p_scat_ratio(d_nm, n)`: ... (physics and units of the binding)
//! fn p_scat_ratio(d_nm: &Dynamic, n: &Dynamic) -> RResult<f64> {
//!     let d_nm = num("p_scat_ratio", "d_nm", d_nm)?;
//!     ...
//! }
//! ```
//! The closure given to `bind` is one line that calls a named function with the binding's
//! name (or a name that contains it), so `help("name")` → family → file → function is a text
//! search. Defaults and limits that a help text states come from one `const` that the help
//! text formats and the code reads. A family is listed once in [`super::FAMILIES`]: the family
//! of a binding is the name of its file.

use super::ctx::Ctx;
use crate::acquire::plan::linspace;
use rhai::{Array, Dynamic, Engine, EvalAltResult, Map, RhaiNativeFunc};
use std::any::{Any, TypeId};
use std::collections::HashSet;
use std::sync::Arc;

pub use super::doc::{fail, Doc, Example, Key, Kind, Opt, Param, RResult, Spec};

/// A type a binding takes or returns: what Rhai stores in a `Dynamic`.
pub trait Value: Any + Clone + Send + Sync {}
impl<T: Any + Clone + Send + Sync> Value for T {}

/// Declares and registers the property getters of one script type, one row a property:
///
/// ```ignore
/// properties!(r, "Image", ImageRef, IMG, [
///     rows: "int", ""; "number of rows"; "img.rows" => "21"; |i| i.0.rows() as INT,
/// ]);
/// ```
/// reads `name: return type, what it returns (units); summary; example => expected; accessor`.
/// Each example is the setup line (`IMG`, which makes the value) and the row's code after a
/// space; the accessor gets `&mut` the Rust type (`ImageRef`). A row is one
/// [`Registrar::getter`] of `Doc::property(type, name)`; a property with a help text or more
/// than one example is declared with `getter` itself.
macro_rules! properties {
    ($r:expr, $ty:literal, $rust:ty, $setup:expr, [$(
        $name:ident: $rty:literal, $rdoc:expr; $summary:expr; $code:expr => $expect:expr; $get:expr,
    )*]) => {$(
        $r.getter::<$rust, _>(
            $crate::script::registry::Doc::property($ty, stringify!($name))
                .returns($rty, $rdoc)
                .summary($summary)
                .example(&format!("{} {}", $setup, $code), $expect),
            $get,
        );
    )*};
}
pub(crate) use properties;

/// A Rhai map of some fields of a value, each under its own name and converted with `.into()`:
/// `fields_map!(r; sx, sy, sz)` is `#{sx: r.sx, sy: r.sy, sz: r.sz}`. A key that is not a
/// field's name, or a value that needs more than `.into()` (a count as `INT`), is inserted
/// after.
macro_rules! fields_map {
    ($v:expr; $($f:ident),+ $(,)?) => {{
        let mut m = rhai::Map::new();
        $(m.insert(stringify!($f).into(), ($v).$f.into());)+
        m
    }};
}
pub(crate) use fields_map;

/// A registration function that calls a family's binding functions (each
/// `fn(&mut Registrar)`: one command, or a few that belong together) in order:
/// `binding_list! { pub fn register { bind_help, bind_numbers } }`.
macro_rules! binding_list {
    ($vis:vis fn $name:ident { $($bind:ident),+ $(,)? }) => {
        $vis fn $name(r: &mut $crate::script::registry::Registrar) {
            $($bind(r);)+
        }
    };
}
pub(crate) use binding_list;

/// A binding body that reads the session and borrows its three arguments (as one tuple)
/// before its options map ([`Registrar::bind_ctx_opts3`]).
pub type Body3<A, B, C, R> = fn(&Ctx, &Spec, (&A, &B, &C), &Map) -> RResult<R>;

/// Hands a family file the engine, the context and the list of declarations.
pub struct Registrar<'a> {
    engine: &'a mut Engine,
    docs: &'a mut Vec<Doc>,
    ctx: Arc<Ctx>,
    /// The family being registered: its name in `FAMILIES`, which is its file
    /// `src/script/<family>.rs`. Every declaration gets it.
    family: &'static str,
    /// (name, parameter types) of every form registered by `bind`/`overload`: an explicit form
    /// is never replaced by an integer form (see [`Registrar::int_forms`]).
    explicit: HashSet<(String, Vec<TypeId>)>,
}

/// The parameter types of a native function (the value's type first for a method).
fn param_types_of<
    A: 'static,
    const N: usize,
    const X: bool,
    R: 'static,
    const F: bool,
    G: RhaiNativeFunc<A, N, X, R, F>,
>(
    _: &G,
) -> [TypeId; N] {
    G::param_types()
}

/// Most float parameters of one form that get integer forms (2^k − 1 of them).
const MAX_INT_FORMS_FLOATS: usize = 5;

impl<'a> Registrar<'a> {
    pub fn new(engine: &'a mut Engine, docs: &'a mut Vec<Doc>, ctx: Arc<Ctx>) -> Self {
        Self {
            engine,
            docs,
            ctx,
            family: "",
            explicit: HashSet::new(),
        }
    }

    /// Integers are accepted wherever a binding takes a float: for a form `name(…, f64, …)`,
    /// the forms with an `i64` in any of its float places are registered too (unless declared
    /// explicitly); they convert the integers and call the float form. So `fibril_diameter(0.55,
    /// 80)` is `fibril_diameter(0.55, 80.0)`, and no "wrong arguments (f64, i64)" reaches the
    /// user. `method`: the first argument is the value a method is called on.
    fn int_forms(&mut self, name: &str, method: bool, types: &[TypeId]) {
        self.explicit.insert((name.to_string(), types.to_vec()));
        let floats: Vec<usize> = (0..types.len())
            .filter(|&i| types[i] == TypeId::of::<f64>())
            .collect();
        if floats.is_empty() || floats.len() > MAX_INT_FORMS_FLOATS {
            return;
        }
        for mask in 1u32..(1 << floats.len()) {
            let conv: Vec<usize> = floats
                .iter()
                .enumerate()
                .filter(|(k, _)| (mask >> k) & 1 == 1)
                .map(|(_, &i)| i)
                .collect();
            let mut ts = types.to_vec();
            for &i in &conv {
                ts[i] = TypeId::of::<i64>();
            }
            if self.explicit.contains(&(name.to_string(), ts.clone())) {
                continue;
            }
            let n = name.to_string();
            self.engine
                .register_raw_fn(name, ts, move |ctx, args| -> RResult<Dynamic> {
                    let mut as_float: Vec<Dynamic> = conv
                        .iter()
                        .map(|&i| Dynamic::from_float(args[i].as_int().unwrap_or_default() as f64))
                        .collect();
                    let mut next = as_float.iter_mut();
                    let mut refs: Vec<&mut Dynamic> = Vec::with_capacity(args.len());
                    for (i, a) in args.iter_mut().enumerate() {
                        if conv.contains(&i) {
                            refs.extend(next.next());
                        } else {
                            refs.push(&mut **a);
                        }
                    }
                    ctx.call_native_fn_raw(&n, method, &mut refs)
                });
        }
    }
    /// Declarations from now on belong to `family` (the `FAMILIES` loop calls this).
    pub fn begin_family(&mut self, family: &'static str) {
        self.family = family;
    }
    /// The shared context (instrument, limits, abort flag, session folder...), to capture in
    /// binding closures.
    pub fn ctx(&self) -> Arc<Ctx> {
        self.ctx.clone()
    }
    /// The engine, for registrations that are not bindings of their own (types, operators).
    pub fn engine(&mut self) -> &mut Engine {
        self.engine
    }

    fn push(&mut self, mut doc: Doc) {
        doc.family = self.family.to_string();
        debug_assert!(
            !self
                .docs
                .iter()
                .any(|d| d.name == doc.name && d.kind == doc.kind),
            "binding {} declared twice",
            doc.name
        );
        self.docs.push(doc);
    }

    /// Declare and register a function or method (Rhai name = `doc.name`).
    pub fn bind<A: 'static, const N: usize, const X: bool, R: Value, const F: bool>(
        &mut self,
        doc: Doc,
        f: impl RhaiNativeFunc<A, N, X, R, F> + Send + Sync + 'static,
    ) {
        // The closure takes what the declaration says: the value for a method, then the
        // declared arguments, with or without the optional ones (the other forms are overloads).
        let this = usize::from(matches!(doc.kind, Kind::Method { .. }));
        let required = doc.params.iter().filter(|p| !p.optional).count() + this;
        let all = doc.params.len() + this;
        debug_assert!(
            (required..=all).contains(&N),
            "{}: the closure takes {N} arguments, the declaration {required} to {all}",
            doc.name
        );
        let types = param_types_of(&f);
        let method = this == 1;
        self.engine.register_fn(doc.name.as_str(), f);
        let name = doc.name.clone();
        self.push(doc);
        self.int_forms(&name, method, &types);
    }

    /// Declare and register a binding whose closure needs the session context: `make` gets the
    /// context and returns the closure, e.g. `r.bind_ctx(d, |c| move || pwd(&c))`.
    pub fn bind_ctx<
        A: 'static,
        const N: usize,
        const X: bool,
        R: Value,
        const F: bool,
        G: RhaiNativeFunc<A, N, X, R, F> + Send + Sync + 'static,
    >(
        &mut self,
        doc: Doc,
        make: impl FnOnce(Arc<Ctx>) -> G,
    ) {
        let f = make(self.ctx());
        self.bind(doc, f);
    }

    /// Declare and register a binding whose one argument is a map of the declared keys, its
    /// body reading the session: `f(ctx, spec, map)`, e.g. `r.bind_map(d, set_optics)`.
    pub fn bind_map<R: Value>(&mut self, doc: Doc, f: fn(&Ctx, &Spec, &Map) -> RResult<R>) {
        let (c, spec) = (self.ctx(), doc.spec());
        self.bind(doc, move |m: Map| f(&c, &spec, &m));
    }

    /// As [`Registrar::bind_opts0`], for a body that reads the session: `f(ctx, spec, opts)`.
    pub fn bind_ctx_opts0<R: Value>(&mut self, doc: Doc, f: fn(&Ctx, &Spec, &Map) -> RResult<R>) {
        let c = self.ctx();
        self.bind_opts0(doc, move |spec, m| f(&c, spec, m));
    }

    /// As [`Registrar::bind_opts`], for a body that reads the session and borrows its argument:
    /// `f(ctx, spec, &a, opts)`, e.g. `r.bind_ctx_opts(d, max_sens)`.
    pub fn bind_ctx_opts<A: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: fn(&Ctx, &Spec, &A, &Map) -> RResult<R>,
    ) {
        let c = self.ctx();
        self.bind_opts(doc, move |spec, a: A, m| f(&c, spec, &a, m));
    }

    /// As [`Registrar::bind_opts2`], for a body that reads the session and borrows its two
    /// arguments: `f(ctx, spec, &a, &b, opts)`, e.g. `r.bind_ctx_opts2(d, fit_beads_of)`.
    pub fn bind_ctx_opts2<A: Value, B: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: fn(&Ctx, &Spec, &A, &B, &Map) -> RResult<R>,
    ) {
        let c = self.ctx();
        self.bind_opts2(doc, move |spec, a: A, b: B, m| f(&c, spec, &a, &b, m));
    }

    /// As [`Registrar::bind_opts3`], for a body that reads the session and borrows its three
    /// arguments (as one tuple): `f(ctx, spec, (&a, &b, &c), opts)`.
    pub fn bind_ctx_opts3<A: Value, B: Value, C: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: Body3<A, B, C, R>,
    ) {
        let ctx = self.ctx();
        self.bind_opts3(doc, move |spec, a: A, b: B, c: C, m| {
            f(&ctx, spec, (&a, &b, &c), m)
        });
    }

    /// Declare and register a binding whose last argument is its optional options map
    /// ([`Doc::opts`]) after one argument `a`: the form with the map and the form without it
    /// (an empty map) both call `f(spec, a, opts)`, `spec` the declaration's keys and usage.
    pub fn bind_opts<A: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: impl Fn(&Spec, A, &Map) -> RResult<R> + Send + Sync + 'static,
    ) {
        let (name, spec, f) = (doc.name.clone(), doc.spec(), Arc::new(f));
        let (s2, f2) = (spec.clone(), f.clone());
        self.bind(doc, move |a: A, m: Map| f(&spec, a, &m));
        self.overload(&name, move |a: A| f2(&s2, a, &Map::new()));
    }

    /// As [`Registrar::bind_opts`], for a binding with no argument before its options map.
    pub fn bind_opts0<R: Value>(
        &mut self,
        doc: Doc,
        f: impl Fn(&Spec, &Map) -> RResult<R> + Send + Sync + 'static,
    ) {
        let (name, spec, f) = (doc.name.clone(), doc.spec(), Arc::new(f));
        let (s2, f2) = (spec.clone(), f.clone());
        self.bind(doc, move |m: Map| f(&spec, &m));
        self.overload(&name, move || f2(&s2, &Map::new()));
    }

    /// As [`Registrar::bind_opts`], for a binding with two arguments before its options map.
    pub fn bind_opts2<A: Value, B: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: impl Fn(&Spec, A, B, &Map) -> RResult<R> + Send + Sync + 'static,
    ) {
        let (name, spec, f) = (doc.name.clone(), doc.spec(), Arc::new(f));
        let (s2, f2) = (spec.clone(), f.clone());
        self.bind(doc, move |a: A, b: B, m: Map| f(&spec, a, b, &m));
        self.overload(&name, move |a: A, b: B| f2(&s2, a, b, &Map::new()));
    }

    /// As [`Registrar::bind_opts`], for a binding with three arguments before its options map.
    pub fn bind_opts3<
        A: Any + Clone + Send + Sync,
        B: Any + Clone + Send + Sync,
        C: Any + Clone + Send + Sync,
        R: Any + Clone + Send + Sync,
    >(
        &mut self,
        doc: Doc,
        f: impl Fn(&Spec, A, B, C, &Map) -> RResult<R> + Send + Sync + 'static,
    ) {
        let (name, spec, f) = (doc.name.clone(), doc.spec(), Arc::new(f));
        let (s2, f2) = (spec.clone(), f.clone());
        self.bind(doc, move |a: A, b: B, c: C, m: Map| f(&spec, a, b, c, &m));
        self.overload(&name, move |a: A, b: B, c: C| f2(&s2, a, b, c, &Map::new()));
    }

    /// Register another form (arity or argument types) of an already declared binding.
    pub fn overload<A: 'static, const N: usize, const X: bool, R: Value, const F: bool>(
        &mut self,
        name: &str,
        f: impl RhaiNativeFunc<A, N, X, R, F> + Send + Sync + 'static,
    ) {
        debug_assert!(
            self.docs.iter().any(|d| d.name == name),
            "overload of undeclared {name}"
        );
        let types = param_types_of(&f);
        let method = self
            .docs
            .iter()
            .any(|d| d.name == name && matches!(d.kind, Kind::Method { .. }));
        self.engine.register_fn(name, f);
        self.int_forms(name, method, &types);
    }

    /// Declare and register a property getter `value.name`.
    pub fn getter<T: Value, R: Value>(
        &mut self,
        doc: Doc,
        f: impl Fn(&mut T) -> R + Send + Sync + 'static,
    ) {
        self.engine.register_get(doc.name.as_str(), f);
        self.push(doc);
    }

    /// Declare and register property getters of the type `ty` that share one accessor and whose
    /// summary is what they return (`returns`): one row `(name, what)` a property;
    /// `example(name)` gives a row's example and its expected value, `get(value, name)` its value.
    pub fn named_getters<T: Value, R: Value>(
        &mut self,
        ty: &str,
        returns: &str,
        rows: &[(&'static str, &str)],
        example: impl Fn(&str) -> (String, &'static str),
        get: fn(&T, &str) -> R,
    ) {
        for &(name, what) in rows {
            let (code, expect) = example(name);
            let d = Doc::property(ty, name)
                .returns(returns, what)
                .summary(what)
                .example(&code, expect);
            self.getter(d, move |v: &mut T| get(v, name));
        }
    }

    /// Declare something registered by hand through [`Registrar::engine`] (operators).
    pub fn declare(&mut self, doc: Doc) {
        self.push(doc);
    }
}

/// The numbers of an array argument (`who: name[i] must be a number` otherwise). Non-finite
/// values pass through: reductions skip them, checks that need finite values make their own.
pub fn numbers(who: &str, name: &str, v: &Dynamic) -> RResult<Vec<f64>> {
    array_of(who, name, "numbers", v, |i, x| {
        to_f64(x).map_or_else(
            || {
                fail(format!(
                    "{who}: {name}[{i}] must be a number, got {} {x}",
                    x.type_name()
                ))
            },
            Ok,
        )
    })
}

/// Every element of an array argument through `item(index, element)`; not an array:
/// `who: name must be an array of <what>, got <type>`.
pub fn array_of<T>(
    who: &str,
    name: &str,
    what: &str,
    v: &Dynamic,
    item: impl FnMut(usize, &Dynamic) -> RResult<T>,
) -> RResult<Vec<T>> {
    let Some(a) = v.read_lock::<rhai::Array>() else {
        return fail(format!(
            "{who}: {name} must be an array of {what}, got {}",
            v.type_name()
        ));
    };
    let mut item = item;
    a.iter().enumerate().map(|(i, x)| item(i, x)).collect()
}

/// A script error `who: e` from any displayable error of the library.
pub fn err(who: &str, e: impl std::fmt::Display) -> Box<EvalAltResult> {
    format!("{who}: {e}").into()
}

/// Number from an int or float argument; the message names the binding, the argument and the
/// value.
pub fn num(who: &str, name: &str, v: &Dynamic) -> RResult<f64> {
    let x = to_f64(v)
        .ok_or_else(|| format!("{who}: {name} must be a number, got {} {v}", v.type_name()))?;
    if x.is_finite() {
        Ok(x)
    } else {
        fail(format!("{who}: {name} = {x} is not a finite number"))
    }
}

/// An integer argument (a float with an integral value is accepted).
pub fn int(who: &str, name: &str, v: &Dynamic) -> RResult<i64> {
    if let Ok(i) = v.as_int() {
        return Ok(i);
    }
    match v.as_float() {
        Ok(f) if f.fract() == 0.0 && f.abs() < 9e15 => Ok(f as i64),
        _ => fail(format!(
            "{who}: {name} must be an integer, got {} {v}",
            v.type_name()
        )),
    }
}

/// A count or seed from a script: `v` if it is ≥ 0, else an error naming `who`, `name` and `v`.
pub fn non_negative(who: &str, name: &str, v: i64) -> RResult<u64> {
    u64::try_from(v).or_else(|_| fail(format!("{who}: {name} = {v} is out of range: {name} ≥ 0")))
}

pub fn to_f64(v: &Dynamic) -> Option<f64> {
    v.as_float()
        .ok()
        .or_else(|| v.as_int().ok().map(|i| i as f64))
}

/// Checked access to a map argument against the declared keys.
pub struct Opts<'a> {
    spec: &'a Spec,
    map: &'a Map,
}

impl<'a> Opts<'a> {
    /// Refuses keys that were not declared (typos), naming the allowed ones.
    pub fn new(spec: &'a Spec, map: &'a Map) -> RResult<Opts<'a>> {
        for k in map.keys() {
            if !spec.keys.iter().any(|d| d == k.as_str()) {
                return fail(format!(
                    "{}: unknown key `{k}`{}; allowed keys: {}; usage: {}",
                    spec.name,
                    super::words::suggestion(k, spec.keys.iter().map(|s| s.as_str())),
                    spec.keys.join(", "),
                    spec.usage
                ));
            }
        }
        Ok(Opts { spec, map })
    }
    /// The value of a declared key. A binding that reads a key it did not declare (a typo in
    /// the code, which would silently fall back to the default) panics in debug builds, so the
    /// example tests catch it.
    fn get(&self, key: impl Key) -> Option<&'a rhai::Dynamic> {
        let key = key.key();
        debug_assert!(
            self.spec.keys.iter().any(|d| d == key),
            "{}: the code reads option `{key}`, which its declaration does not have (declared: {})",
            self.spec.name,
            self.spec.keys.join(", ")
        );
        self.map.get(key)
    }
    /// The raw value of a declared key (for keys whose type is a script object, e.g. a Scan).
    pub fn value(&self, key: impl Key) -> Option<&'a rhai::Dynamic> {
        let key = key.key();
        self.get(key)
    }
    pub fn has(&self, key: impl Key) -> bool {
        let key = key.key();
        self.get(key).is_some()
    }
    fn missing<T>(&self, key: &str) -> RResult<T> {
        fail(format!(
            "{}: missing key `{key}`; usage: {}",
            self.spec.name, self.spec.usage
        ))
    }
    pub fn f64(&self, key: impl Key) -> RResult<Option<f64>> {
        let key = key.key();
        self.get(key)
            .map(|v| num(&self.spec.name, key, v))
            .transpose()
    }
    pub fn f64_or(&self, key: impl Key, default: f64) -> RResult<f64> {
        let key = key.key();
        Ok(self.f64(key)?.unwrap_or(default))
    }
    pub fn req_f64(&self, key: impl Key) -> RResult<f64> {
        let key = key.key();
        match self.f64(key)? {
            Some(v) => Ok(v),
            None => self.missing(key),
        }
    }
    pub fn int(&self, key: impl Key) -> RResult<Option<i64>> {
        let key = key.key();
        self.get(key)
            .map(|v| int(&self.spec.name, key, v))
            .transpose()
    }
    pub fn req_int(&self, key: impl Key) -> RResult<i64> {
        let key = key.key();
        match self.int(key)? {
            Some(v) => Ok(v),
            None => self.missing(key),
        }
    }
    pub fn bool_or(&self, key: impl Key, default: bool) -> RResult<bool> {
        let key = key.key();
        match self.get(key) {
            None => Ok(default),
            Some(v) => v.as_bool().or_else(|_| {
                fail(format!(
                    "{}: {key} must be true or false, got {} {v}",
                    self.spec.name,
                    v.type_name()
                ))
            }),
        }
    }
    pub fn string(&self, key: impl Key) -> RResult<Option<String>> {
        let key = key.key();
        match self.get(key) {
            None => Ok(None),
            Some(v) if v.is_string() => Ok(Some(v.to_string())),
            Some(v) => fail(format!(
                "{}: {key} must be a string, got {} {v}",
                self.spec.name,
                v.type_name()
            )),
        }
    }
    /// `#{x: "…", y: "…", z: "…"}`: one string per axis (all three required).
    pub fn axis_strings(&self, key: impl Key) -> RResult<Option<[String; 3]>> {
        let key = key.key();
        let Some(v) = self.get(key) else {
            return Ok(None);
        };
        let bad = |why: &str| {
            fail(format!(
                "{}: {key} must be #{{x: \"…\", y: \"…\", z: \"…\"}} ({why}), got {v}",
                self.spec.name
            ))
        };
        let Some(m) = v.read_lock::<rhai::Map>() else {
            return bad("a map");
        };
        if let Some(k) = m.keys().find(|k| !["x", "y", "z"].contains(&k.as_str())) {
            return bad(&format!("unknown axis `{k}`"));
        }
        let mut out: [String; 3] = Default::default();
        for (i, a) in ["x", "y", "z"].iter().enumerate() {
            match m.get(*a) {
                Some(s) if s.is_string() => out[i] = s.to_string(),
                Some(_) => return bad(&format!("{a} must be a string")),
                None => return bad(&format!("{a} is missing")),
            }
        }
        Ok(Some(out))
    }
    /// `[from, to]` (µm).
    pub fn range(&self, key: impl Key) -> RResult<Option<(f64, f64)>> {
        let key = key.key();
        let Some(v) = self.get(key) else {
            return Ok(None);
        };
        let bad = || {
            fail(format!(
                "{}: {key} must be [from, to] (two numbers, µm), got {v}; usage: {}",
                self.spec.name, self.spec.usage
            ))
        };
        let Some(a) = v.read_lock::<rhai::Array>() else {
            return bad();
        };
        if a.len() != 2 {
            return bad();
        }
        let who = &self.spec.name;
        Ok(Some((
            num(who, &format!("{key}[0]"), &a[0])?,
            num(who, &format!("{key}[1]"), &a[1])?,
        )))
    }
    pub fn req_range(&self, key: impl Key) -> RResult<(f64, f64)> {
        let key = key.key();
        match self.range(key)? {
            Some(v) => Ok(v),
            None => self.missing(key),
        }
    }
}

/// `help()` listing: one line per binding, grouped by family (in registration order).
pub fn help_index(docs: &[Doc]) -> String {
    let mut families: Vec<&str> = vec![];
    for d in docs {
        if !families.contains(&d.family.as_str()) {
            families.push(&d.family);
        }
    }
    let mut s = String::new();
    for f in families {
        s.push_str(&format!("{f}\n"));
        for d in docs.iter().filter(|d| d.family == f) {
            s.push_str(&format!("  {}\n", d.one_line()));
        }
    }
    s.push_str("\nhelp(\"name\") for arguments, units and examples.\n");
    s
}

/// Find a declaration by name (functions first, then methods/properties), case-insensitive
/// fallback; `img.max` / `scan.sx` style names also work.
pub fn find<'d>(docs: &'d [Doc], name: &str) -> Vec<&'d Doc> {
    let name = name.trim().trim_end_matches("()");
    let (ty, n) = match name.split_once('.') {
        Some((t, n)) => (Some(t.to_ascii_lowercase()), n),
        None => (None, name),
    };
    let mut hits: Vec<&Doc> = docs
        .iter()
        .filter(|d| d.name == n)
        .filter(|d| match (&ty, &d.kind) {
            (None, _) => true,
            (Some(t), Kind::Method { ty } | Kind::Property { ty } | Kind::Operator { ty }) => {
                ty.to_ascii_lowercase() == *t || Doc::receiver(ty) == *t
            }
            (Some(_), Kind::Function) => false,
        })
        .collect();
    if hits.is_empty() {
        hits = docs
            .iter()
            .filter(|d| d.name.eq_ignore_ascii_case(n) || d.family.eq_ignore_ascii_case(name))
            .collect();
    }
    hits
}

/// `docs/api.md`, generated from the declarations.
pub fn api_markdown(docs: &[Doc]) -> String {
    let mut s = String::from(
        "# bfpscope script API\n\n\
         Generated from the binding declarations by `bfpscope docs`; do not edit by hand \
         (a test fails when this file is stale).\n\n\
         Units at the script boundary: positions and lengths in µm, diameters and wavelengths \
         in nm, power in mW, time in s. Every example below is run by the test suite and its \
         result checked (examples that need an instrument run against the mock instrument, \
         `connect(#{backend: \"mock\"})`).\n\n",
    );
    let mut families: Vec<&str> = vec![];
    for d in docs {
        if !families.contains(&d.family.as_str()) {
            families.push(&d.family);
        }
    }
    s.push_str("## Contents\n\n");
    for f in &families {
        let names: Vec<String> = docs
            .iter()
            .filter(|d| d.family == *f)
            .map(|d| format!("[`{}`](#{})", d.name, anchor(d)))
            .collect();
        s.push_str(&format!("- **{f}**: {}\n", names.join(", ")));
    }
    for f in &families {
        s.push_str(&format!("\n## {f}\n"));
        for d in docs.iter().filter(|d| d.family == *f) {
            s.push_str(&format!(
                "\n<a id=\"{}\"></a>\n### `{}`\n\n",
                anchor(d),
                d.signature()
            ));
            s.push_str(&format!("{}\n\n", d.summary));
            if !d.forms.is_empty() {
                s.push_str(&format!(
                    "Forms: `{}`\n\n",
                    d.usage().replace("  |  ", "`, `")
                ));
            }
            let rows: Vec<&Param> = d.params.iter().collect();
            if !rows.is_empty() {
                s.push_str("| argument | type | unit | description |\n|---|---|---|---|\n");
                for p in rows {
                    s.push_str(&md_row(p, ""));
                    for k in &p.keys {
                        s.push_str(&md_row(k, &format!("{}.", p.name)));
                    }
                }
                s.push('\n');
            }
            if d.returns.0 != "()" || !d.returns.1.is_empty() {
                s.push_str(&format!("Returns: `{}` {}\n\n", d.returns.0, d.returns.1));
            }
            if !d.help.is_empty() {
                s.push_str(d.help.trim());
                s.push_str("\n\n");
            }
            if !d.examples.is_empty() {
                s.push_str("```rhai\n");
                for e in &d.examples {
                    s.push_str(&format!("{}\n// → {}\n", e.code, e.expect));
                }
                s.push_str("```\n");
            }
        }
    }
    s
}

fn anchor(d: &Doc) -> String {
    match &d.kind {
        Kind::Function => d.name.clone(),
        Kind::Method { ty } | Kind::Property { ty } | Kind::Operator { ty } => {
            format!("{}-{}", ty.to_ascii_lowercase(), d.name)
        }
    }
}

fn md_row(p: &Param, prefix: &str) -> String {
    let opt = if p.optional && !p.doc.starts_with("optional") {
        " (optional)"
    } else {
        ""
    };
    format!(
        "| `{prefix}{}` | {} | {} | {}{opt} |\n",
        p.name,
        p.ty.replace('|', "\\|"),
        p.unit,
        p.doc.replace('|', "\\|")
    )
}

/// `[[x, y], ...]` → polyline.
pub fn points(who: &str, v: &Dynamic) -> RResult<Vec<[f64; 2]>> {
    let Some(a) = v.read_lock::<Array>() else {
        return fail(format!(
            "{who}: points must be an array of [x, y] pairs (µm), got {v}"
        ));
    };
    a.iter()
        .enumerate()
        .map(|(i, p)| {
            let what = format!("points[{i}]");
            number_pair(who, &what, p, "[x, y] (µm)", "must have 2 numbers [x, y]")
        })
        .collect()
}

/// The two numbers of the array `v` (`what` it is in the errors, `points[3]` or `x`): refused
/// unless an array (`{what} must be {must_be}`) of two (`{what} {two}, got n values`) numbers.
pub fn number_pair(
    who: &str,
    what: &str,
    v: &Dynamic,
    must_be: &str,
    two: &str,
) -> RResult<[f64; 2]> {
    let Some(a) = v.read_lock::<Array>() else {
        return fail(format!("{who}: {what} must be {must_be}, got {v}"));
    };
    if a.len() != 2 {
        return fail(format!("{who}: {what} {two}, got {} values", a.len()));
    }
    Ok([
        num(who, &format!("{what}[0]"), &a[0])?,
        num(who, &format!("{what}[1]"), &a[1])?,
    ])
}

/// The `x: [from, to], y: [from, to], nx, ny` keys of a grid map → regular axes (µm).
pub fn grid_axes(who: &str, o: &Opts) -> RResult<(Vec<f64>, Vec<f64>)> {
    let (x0, x1) = o.req_range("x")?;
    let (y0, y1) = o.req_range("y")?;
    let nx = o.req_int("nx")?;
    let ny = o.req_int("ny")?;
    for (k, v) in [("nx", nx), ("ny", ny)] {
        if !(1..=4096).contains(&v) {
            return fail(format!("{who}: {k} = {v} is out of range: 1 ≤ {k} ≤ 4096"));
        }
    }
    Ok((linspace(x0, x1, nx as usize), linspace(y0, y1, ny as usize)))
}
