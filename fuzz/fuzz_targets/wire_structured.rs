//! Structured commands: `arbitrary` builds JSON-ish commands (bare arrays,
//! `{"ch": [...], "seq": N}`, named channels from the model, with numbers in
//! many spellings and wrong values mixed in), serialises them, and checks
//! `protocol::parse` against an independent reading of the README's rules:
//!
//! - a command with nothing wrong is accepted, with every value it gives
//!   (clamped to its channel) and every other channel at its default, and the
//!   encoded frame decodes back to exactly those values;
//! - a command with something wrong is rejected for one of the reasons that
//!   apply to it;
//! - `units` and `norm` values map by the README's formula (within 1 ns: the
//!   value as JSON text may parse one ulp away from the generator's f64).
#![no_main]

use arbitrary::Arbitrary;
use libfuzzer_sys::fuzz_target;
use ppm_fuzz::{mapped_ns, models, parse_checked};
use ppm_shared::frame::FrameModel;
use ppm_shared::protocol::RejectReason::{self, *};

/// A JSON number in one of many spellings.
#[derive(Arbitrary, Debug, Clone, Copy)]
enum Num {
    /// Whole microseconds.
    Int(i16),
    /// `us.mmm`.
    Milli(u16, u16),
    /// `m e k` with k in -3..=3 (`15e2`, `15005E-1`, `2.5e+3` style).
    Exp(u16, u8),
    /// Any float, written the way Rust writes it.
    Float(f64),
    /// One of the hand-picked spellings in `SPECIAL`.
    Special(u8),
    /// A large unsigned integer (a plausible `seq`).
    Big(u64),
    /// Thousandths, `-1.250` (a plausible `norm` or `units` value).
    Frac(i16),
}

/// What parsing a number's text yields.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Class {
    /// Not JSON at all.
    BadJson,
    /// A number beyond a 64-bit float (`1e400`): `out_of_range` wherever it
    /// stands, since the JSON cannot be read.
    BeyondF64,
    /// A number: its value in ns (read as microseconds) when exactly
    /// known; its value (within an ulp), and its `as_u64`.
    Number {
        ns: Option<u64>,
        us: f64,
        u64: Option<u64>,
    },
}

/// (text, value in us when a number (NaN: not JSON, infinity: beyond a
/// 64-bit float), exact ns, as_u64)
const SPECIAL: &[(&str, f64, Option<u64>, Option<u64>)] = &[
    ("500", 500.0, Some(500_000), Some(500)),
    ("2500", 2500.0, Some(2_500_000), Some(2500)),
    ("2500.0", 2500.0, Some(2_500_000), None),
    ("499.999", 499.999, Some(499_999), None),
    ("2500.001", 2500.001, Some(2_500_001), None),
    ("-0", -0.0, Some(0), None),
    ("0", 0.0, Some(0), Some(0)),
    ("-1500", -1500.0, None, None),
    (
        "18446744073709551615",
        u64::MAX as f64,
        None,
        Some(u64::MAX),
    ),
    ("18446744073709551616", u64::MAX as f64, None, None),
    ("1e3", 1000.0, Some(1_000_000), None),
    ("2.5e3", 2500.0, Some(2_500_000), None),
    ("5E2", 500.0, Some(500_000), None),
    ("0.15e4", 1500.0, Some(1_500_000), None),
    ("1500.0004999", 1500.0004999, Some(1_500_000), None),
    ("2500.0000000000001", 2500.0, Some(2_500_000), None),
    ("499.99999999999999", 500.0, Some(500_000), None),
    ("-1e-400", -0.0, Some(0), None),
    ("1e-400", 0.0, Some(0), None),
    ("1e300", 1e300, None, None),
    ("1e400", f64::INFINITY, None, None),
    ("-1e400", f64::INFINITY, None, None),
    ("01500", f64::NAN, None, None),
    ("1500.", f64::NAN, None, None),
    (".5", f64::NAN, None, None),
    ("+1500", f64::NAN, None, None),
    ("0x5DC", f64::NAN, None, None),
    ("NaN", f64::NAN, None, None),
    ("Infinity", f64::NAN, None, None),
    ("1_500", f64::NAN, None, None),
    ("1500e", f64::NAN, None, None),
];

impl Num {
    fn render(self) -> (String, Class) {
        match self {
            Num::Int(i) => (
                i.to_string(),
                Class::Number {
                    ns: (i >= 0).then(|| i as u64 * 1000),
                    us: i as f64,
                    u64: (i >= 0).then_some(i as u64),
                },
            ),
            Num::Milli(us, m) => {
                let m = m % 1000;
                (
                    format!("{us}.{m:03}"),
                    Class::Number {
                        ns: Some(us as u64 * 1000 + m as u64),
                        us: us as f64 + m as f64 / 1000.0,
                        u64: None,
                    },
                )
            }
            Num::Exp(m, k) => {
                let e = (k % 7) as i32 - 3;
                let spell = ["e", "E", "e+", "E+"][(k / 7 % 4) as usize];
                let text = if e < 0 {
                    format!("{m}e{e}")
                } else {
                    format!("{m}{spell}{e}")
                };
                let ns = m as u64 * 10u64.pow((e + 3) as u32);
                (
                    text,
                    Class::Number {
                        ns: Some(ns),
                        us: ns as f64 / 1000.0,
                        u64: None,
                    },
                )
            }
            Num::Float(f) => {
                // Rust prints the shortest text that reads back as `f`, and
                // serde_json (with float_roundtrip, as the workspace builds
                // it) reads it back exactly, even next to the 500/2500 us
                // bounds and at the largest finite doubles.
                let text = format!("{f}");
                if !f.is_finite() {
                    return (text, Class::BadJson);
                }
                let integral =
                    f.fract() == 0.0 && text.bytes().all(|b| b.is_ascii_digit() || b == b'-');
                let ns = (f == 500.0 || f == 2500.0).then_some((f * 1000.0) as u64);
                let u64 = if integral && f >= 0.0 && !text.starts_with('-') {
                    text.parse::<u64>().ok()
                } else {
                    None
                };
                (text, Class::Number { ns, us: f, u64 })
            }
            Num::Special(k) => {
                let (text, us, ns, u64) = SPECIAL[k as usize % SPECIAL.len()];
                let class = if us.is_nan() {
                    Class::BadJson
                } else if us.is_infinite() {
                    Class::BeyondF64
                } else {
                    Class::Number { ns, us, u64 }
                };
                (text.to_string(), class)
            }
            Num::Big(u) => (
                u.to_string(),
                Class::Number {
                    ns: None,
                    us: u as f64,
                    u64: Some(u),
                },
            ),
            Num::Frac(t) => {
                let a = t.unsigned_abs();
                let sign = if t < 0 { "-" } else { "" };
                (
                    format!("{sign}{}.{:03}", a / 1000, a % 1000),
                    Class::Number {
                        ns: (t >= 0).then_some(t as u64),
                        us: t as f64 / 1000.0,
                        u64: None,
                    },
                )
            }
        }
    }
}

/// A value where a channel value is expected.
#[derive(Arbitrary, Debug, Clone)]
enum Leaf {
    Num(Num),
    Str(String),
    Null,
    Bool(bool),
    EmptyArr,
    EmptyObj,
    Nested(Num),
}

/// A key of an object command.
#[derive(Arbitrary, Debug, Clone)]
enum Key {
    /// The model's channel `i % channels`.
    Name(u8),
    /// `auxN`, which may or may not exist.
    Aux(u8),
    Seq,
    Ch,
    Get,
    Units,
    Norm,
    /// `to`, the output a command is for (any string, unchecked by `parse`).
    To,
    Other(String),
}

#[derive(Arbitrary, Debug, Clone)]
enum Entry {
    Leaf(Leaf),
    Arr(Vec<Leaf>),
    Obj(Vec<(Key, Leaf)>),
}

#[derive(Arbitrary, Debug, Clone)]
enum Top {
    /// `[n, n, ...]`
    BareNums(Vec<Num>),
    /// `{"ch": [n, ...], "seq": s}` in either key order.
    ChNums(Vec<Num>, Option<Num>, bool),
    /// `{"name": n, ..., "seq": s}`
    NamedNums(Vec<(u8, Num)>, Option<Num>),
    /// `{"units": {"name": x, ...}, "seq": s}` (`true`) or the same with `norm`.
    Mapped(bool, Vec<(u8, Num)>, Option<Num>),
    /// Any array.
    Bare(Vec<Leaf>),
    /// Any object.
    Obj(Vec<(Key, Entry)>),
    /// Not an array or an object.
    Scalar(Leaf),
}

#[derive(Arbitrary, Debug)]
struct Input {
    model: u8,
    top: Top,
    /// Whitespace between tokens, cycled.
    ws: Vec<u8>,
}

/// A JSON value built from the input, with what its numbers parse to.
enum J {
    Num(String, Class),
    Str(String),
    Null,
    Bool(bool),
    Arr(Vec<J>),
    Obj(Vec<(String, J)>),
}

impl J {
    fn num(n: Num) -> J {
        let (t, c) = n.render();
        J::Num(t, c)
    }

    fn leaf(l: &Leaf) -> J {
        match l {
            Leaf::Num(n) => J::num(*n),
            Leaf::Str(s) => J::Str(s.clone()),
            Leaf::Null => J::Null,
            Leaf::Bool(b) => J::Bool(*b),
            Leaf::EmptyArr => J::Arr(vec![]),
            Leaf::EmptyObj => J::Obj(vec![]),
            Leaf::Nested(n) => J::Arr(vec![J::num(*n)]),
        }
    }

    fn has_bad_json(&self) -> bool {
        self.has(Class::BadJson)
    }

    fn has(&self, class: Class) -> bool {
        match self {
            J::Num(_, c) => *c == class,
            J::Arr(v) => v.iter().any(|j| j.has(class)),
            J::Obj(v) => v.iter().any(|(_, j)| j.has(class)),
            _ => false,
        }
    }
}

struct Writer<'a> {
    out: String,
    ws: &'a [u8],
    k: usize,
}

impl Writer<'_> {
    fn space(&mut self) {
        if self.ws.is_empty() {
            return;
        }
        let b = self.ws[self.k % self.ws.len()];
        self.k += 1;
        self.out
            .push_str(["", "", " ", "  ", "\n", "\t", "\r\n", " \n "][b as usize % 8]);
    }

    fn write(&mut self, j: &J) {
        self.space();
        match j {
            J::Num(t, _) => self.out.push_str(t),
            J::Str(s) => self.out.push_str(&serde_json::to_string(s).unwrap()),
            J::Null => self.out.push_str("null"),
            J::Bool(b) => self.out.push_str(if *b { "true" } else { "false" }),
            J::Arr(v) => {
                self.out.push('[');
                for (i, x) in v.iter().enumerate() {
                    if i > 0 {
                        self.out.push(',');
                    }
                    self.write(x);
                }
                self.space();
                self.out.push(']');
            }
            J::Obj(v) => {
                self.out.push('{');
                for (i, (k, x)) in v.iter().enumerate() {
                    if i > 0 {
                        self.out.push(',');
                    }
                    self.space();
                    self.out.push_str(&serde_json::to_string(k).unwrap());
                    self.space();
                    self.out.push(':');
                    self.write(x);
                }
                self.space();
                self.out.push('}');
            }
        }
        self.space();
    }
}

/// Leaves out the keys an object already has: JSON does not define duplicates.
fn dedup(mut obj: Vec<(String, J)>) -> J {
    let mut seen = std::collections::HashSet::new();
    obj.retain(|(k, _)| seen.insert(k.clone()));
    J::Obj(obj)
}

fn build(top: &Top, m: &FrameModel) -> J {
    let name = |i: u8| m.names()[i as usize % m.channels()].clone();
    let key = |k: &Key| match k {
        Key::Name(i) => name(*i),
        Key::Aux(i) => format!("aux{i}"),
        Key::Seq => "seq".into(),
        Key::Ch => "ch".into(),
        Key::Get => "get".into(),
        Key::Units => "units".into(),
        Key::Norm => "norm".into(),
        Key::To => "to".into(),
        Key::Other(s) => s.clone(),
    };
    let mut obj: Vec<(String, J)> = vec![];
    match top {
        Top::BareNums(v) => return J::Arr(v.iter().map(|n| J::num(*n)).collect()),
        Top::Bare(v) => return J::Arr(v.iter().map(J::leaf).collect()),
        Top::Scalar(l) => return J::leaf(l),
        Top::ChNums(v, seq, seq_first) => {
            let ch = (
                "ch".to_string(),
                J::Arr(v.iter().map(|n| J::num(*n)).collect()),
            );
            let seq = seq.map(|s| ("seq".to_string(), J::num(s)));
            if *seq_first {
                obj.extend(seq);
                obj.push(ch);
            } else {
                obj.push(ch);
                obj.extend(seq);
            }
        }
        Top::NamedNums(v, seq) => {
            obj.extend(v.iter().map(|(i, n)| (name(*i), J::num(*n))));
            obj.extend(seq.map(|s| ("seq".to_string(), J::num(s))));
        }
        Top::Mapped(units, v, seq) => {
            let values = dedup(v.iter().map(|(i, n)| (name(*i), J::num(*n))).collect());
            let form = if *units { "units" } else { "norm" };
            obj.push((form.to_string(), values));
            obj.extend(seq.map(|s| ("seq".to_string(), J::num(s))));
        }
        Top::Obj(v) => {
            for (k, e) in v {
                let j = match e {
                    Entry::Leaf(l) => J::leaf(l),
                    Entry::Arr(v) => J::Arr(v.iter().map(J::leaf).collect()),
                    Entry::Obj(v) => dedup(v.iter().map(|(k, l)| (key(k), J::leaf(l))).collect()),
                };
                obj.push((key(k), j));
            }
        }
    }
    dedup(obj)
}

/// A value a command gives a channel.
#[derive(Debug, Clone, Copy)]
enum Given {
    /// Microseconds (the array and named forms).
    Us(Class),
    /// `units` (true) or `norm` (false), and the value.
    Mapped(bool, f64),
}

/// What the README says the command is.
enum Expect {
    /// Accepted: seq, and per channel the value given, if any.
    Ok(Option<u64>, Vec<Option<Given>>),
    /// Rejected for one of these reasons.
    Err(Vec<RejectReason>),
}

fn value_reason(j: &J) -> Option<RejectReason> {
    match j {
        J::Num(_, Class::Number { us, .. }) if (500.0..=2500.0).contains(us) => None,
        J::Num(..) => Some(OutOfRange),
        _ => Some(NotANumber),
    }
}

fn set(i: usize, v: &J, given: &mut [Option<Given>], why: &mut Vec<RejectReason>) {
    match (value_reason(v), v) {
        (Some(r), _) => why.push(r),
        (None, J::Num(_, c)) => given[i] = Some(Given::Us(*c)),
        _ => unreachable!(),
    }
}

fn positional(
    items: &[J],
    m: &FrameModel,
    given: &mut [Option<Given>],
    why: &mut Vec<RejectReason>,
) {
    if items.len() > m.channels() {
        why.push(TooManyValues);
        return;
    }
    for (i, j) in items.iter().enumerate() {
        set(i, j, given, why);
    }
}

fn expect(j: &J, m: &FrameModel) -> Expect {
    // serde_json stops at the first error in the text: a syntax error
    // (invalid_json) or a number beyond a 64-bit float (out_of_range).
    match (j.has_bad_json(), j.has(Class::BeyondF64)) {
        (true, true) => return Expect::Err(vec![InvalidJson, OutOfRange]),
        (true, false) => return Expect::Err(vec![InvalidJson]),
        (false, true) => return Expect::Err(vec![OutOfRange]),
        (false, false) => {}
    }
    let mut given = vec![None; m.channels()];
    let mut why = vec![];
    let mut seq = None;
    match j {
        J::Arr(items) => positional(items, m, &mut given, &mut why),
        J::Obj(entries) => {
            let get = |k: &str| entries.iter().find(|(key, _)| key == k).map(|(_, j)| j);
            match get("seq") {
                Some(J::Num(_, Class::Number { u64: Some(s), .. })) => seq = Some(*s),
                Some(_) => why.push(BadShape),
                None => {}
            }
            // `to` names the output, any string (`parse` checks no name).
            match get("to") {
                Some(J::Str(_)) | None => {}
                Some(_) => why.push(BadShape),
            }
            let form = if get("ch").is_some() {
                "ch"
            } else if get("units").is_some() {
                "units"
            } else if get("norm").is_some() {
                "norm"
            } else {
                ""
            };
            if !form.is_empty()
                && entries
                    .iter()
                    .any(|(k, _)| k != form && k != "seq" && k != "to")
            {
                // One form per command.
                why.push(BadShape);
            }
            match (form, get(form)) {
                ("ch", Some(J::Arr(items))) => positional(items, m, &mut given, &mut why),
                ("units" | "norm", Some(J::Obj(values))) => {
                    let units = form == "units";
                    for (k, v) in values {
                        let Some(i) = m.index_of(k) else {
                            why.push(UnknownChannel);
                            continue;
                        };
                        match v {
                            J::Num(_, Class::Number { us: x, .. }) => {
                                if units && m.unit_range(i).is_none() {
                                    why.push(UnknownChannel);
                                } else {
                                    given[i] = Some(Given::Mapped(units, *x));
                                }
                            }
                            _ => why.push(NotANumber),
                        }
                    }
                }
                ("ch" | "units" | "norm", _) => why.push(BadShape),
                _ => {
                    for (k, v) in entries.iter().filter(|(k, _)| k != "seq" && k != "to") {
                        match m.index_of(k) {
                            None => why.push(UnknownChannel),
                            Some(i) => set(i, v, &mut given, &mut why),
                        }
                    }
                }
            }
        }
        _ => why.push(BadShape),
    }
    if why.is_empty() && given.iter().all(Option::is_none) {
        why.push(BadShape);
    }
    if why.is_empty() {
        Expect::Ok(seq, given)
    } else {
        Expect::Err(why)
    }
}

fuzz_target!(|input: Input| {
    let ms = models();
    let m = &ms[input.model as usize % ms.len()];
    let j = build(&input.top, m);
    let mut w = Writer {
        out: String::new(),
        ws: &input.ws,
        k: 0,
    };
    w.write(&j);
    let text = w.out;
    let got = parse_checked(text.as_bytes(), m);
    match (expect(&j, m), got) {
        (Expect::Err(why), Err(e)) => {
            assert!(
                why.contains(&e.reason),
                "{text}: rejected as {e}, expected one of {why:?}"
            );
        }
        (Expect::Err(why), Ok(cmd)) => {
            panic!("{text}: accepted as {cmd:?}, expected a rejection for one of {why:?}")
        }
        (Expect::Ok(..), Err(e)) => panic!("{text}: rejected as {e}, expected acceptance"),
        (Expect::Ok(seq, given), Ok(cmd)) => {
            assert_eq!(cmd.seq, seq, "{text}");
            let mut clamped = 0;
            let mut exact = true;
            for (i, g) in given.iter().enumerate() {
                let got = cmd.channels.as_ns()[i];
                let (lo, hi) = (m.min_ns(i), m.max_ns(i));
                match g {
                    None => assert_eq!(got, m.default_ns(i), "{text}: channel {i} default"),
                    Some(Given::Us(Class::Number { ns: Some(ns), .. })) => {
                        let want = (*ns).clamp(lo as u64, hi as u64);
                        clamped += (want != *ns) as u32;
                        assert_eq!(got as u64, want, "{text}: channel {i}");
                    }
                    Some(Given::Us(Class::Number { ns: None, us, .. })) => {
                        exact = false;
                        let ns = us * 1000.0;
                        let want = ns.clamp(lo as f64, hi as f64);
                        assert!(
                            (got as f64 - want).abs() <= 1.0,
                            "{text}: channel {i} = {got} ns, expected about {want}"
                        );
                    }
                    Some(Given::Mapped(units, x)) => {
                        exact = false;
                        let (want, _) = mapped_ns(m, i, *units, *x).expect("a unit range");
                        assert!(
                            got.abs_diff(want) <= 1,
                            "{text}: channel {i} = {got} ns, expected {want}"
                        );
                    }
                    Some(Given::Us(Class::BadJson | Class::BeyondF64)) => unreachable!(),
                }
            }
            if exact {
                assert_eq!(cmd.clamped, clamped, "{text}: clamped count");
            }
        }
    }
});
