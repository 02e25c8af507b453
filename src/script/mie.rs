//! Binding family `mie`: Lorenz–Mie efficiencies and the focused-beam Mie response of a sphere.

use super::ctx::Ctx;
use super::keys::{D_NM, N};
use super::registry::{err, fields_map, Doc, Opt, Opts, RResult, Registrar, Spec};
use rhai::{Map, INT};

/// The options of this family's bindings, each key written once (`Opt`).
const M_IM: Opt = Opt::new("m_im", "float", "");
const M_RE: Opt = Opt::new("m_re", "float", "");
const N_IM: Opt = Opt::new("n_im", "float", "");
const X: Opt = Opt::new("x", "float", "");

pub fn register(r: &mut Registrar) {
    let d = Doc::func("mie_q")
        .map(
            "sphere",
            "size parameter and relative index",
            &[
                X.doc("size parameter π d n_medium / λ"),
                M_RE.doc("real part of the relative index"),
                M_IM.doc("optional: absorption, ≥ 0 (default 0)"),
            ],
        )
        .returns("map", "#{qext, qsca, qabs, qback, g, n_terms}")
        .summary("Lorenz–Mie efficiencies of a homogeneous sphere (Bohren & Huffman)")
        .example(
            "let q = mie_q(#{x: 1.0, m_re: 1.5}); round((q.qext - q.qsca) * 1e9)",
            "0.0",
        )
        .example("mie_q(#{x: -1.0, m_re: 1.5})", "error: x");
    let spec = d.spec();
    r.bind(d, move |m: Map| mie_q(&spec, &m));
    let d = Doc::func("mie")
        .map(
            "sphere",
            "a sphere in the medium and wavelength of optics()",
            &[
                D_NM.doc("diameter"),
                N.doc("refractive index"),
                N_IM.doc("optional: absorption part of the index, ≥ 0"),
            ],
        )
        .returns("map", "#{qext, qsca, qabs, qback, g, n_terms, x}")
        .summary("Lorenz–Mie efficiencies of a sphere at the current wavelength")
        .example("mie(#{d_nm: 110.0, n: 1.572}).qsca > 0.0", "true");
    r.bind_map(d, mie);
}

/// `mie_q(#{x, m_re, m_im})`: Lorenz–Mie efficiencies of a sphere of size parameter x and
/// relative index m_re + i·m_im (Bohren & Huffman).
fn mie_q(spec: &Spec, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let q = crate::optics::mie::mie_q(
        o.req_f64(X)?,
        num_complex::Complex64::new(o.req_f64(M_RE)?, o.f64_or(M_IM, 0.0)?),
    )
    .map_err(|e| err("mie_q", e))?;
    Ok(mie_map(&q))
}

/// `mie(#{d_nm, n, n_im})`: efficiencies of a sphere of diameter d_nm (nm) in the medium and at
/// the wavelength of the session's optics; adds the size parameter x = π·d·n_medium/λ.
fn mie(ctx: &Ctx, spec: &Spec, m: &Map) -> RResult<Map> {
    let o = Opts::new(spec, m)?;
    let op = ctx.optics();
    let dn = o.req_f64(D_NM)?;
    let q = crate::optics::mie::sphere(
        dn,
        num_complex::Complex64::new(o.req_f64(N)?, o.f64_or(N_IM, 0.0)?),
        op.n_medium,
        op.wavelength_nm,
    )
    .map_err(|e| err("mie", e))?;
    let mut mm = mie_map(&q);
    mm.insert(
        "x".into(),
        (std::f64::consts::PI * dn * op.n_medium / op.wavelength_nm).into(),
    );
    Ok(mm)
}

fn mie_map(q: &crate::optics::mie::MieResult) -> Map {
    let mut m = fields_map!(q; qext, qsca, qabs, qback, g);
    m.insert("n_terms".into(), (q.n_terms as INT).into());
    m
}
