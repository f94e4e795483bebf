//! The code's shape: within each library crate, modules import each other in
//! one direction only (no file-level import circles), outside their tests.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// The top-level module a file of `src/` belongs to (`line/gpio.rs` is
/// `line`), or `None` for the crate roots, binaries and test files (a
/// `tests.rs`, or any file under a `tests/` folder: tests out of line).
fn module_of(rel: &Path) -> Option<String> {
    let test_file = rel.file_stem().is_some_and(|s| s == "tests")
        || rel.components().any(|c| c.as_os_str() == "tests");
    if test_file {
        return None;
    }
    let first = rel.components().next()?.as_os_str().to_str()?.to_string();
    match first.as_str() {
        "lib.rs" | "main.rs" | "bin" => None,
        f => Some(f.trim_end_matches(".rs").to_string()),
    }
}

/// The `crate::MODULE` paths a file names outside its `#[cfg(test)]` part:
/// the item after the attribute, which is an inline test module to the end
/// of the file, or one line (`mod tests;`, whose file is not read here).
fn imports(text: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        let l = line.trim_start();
        if l.starts_with("#[cfg(test)]") {
            match lines.next().map(str::trim) {
                Some(item) if item.ends_with(';') => continue,
                _ => break,
            }
        }
        if l.starts_with("//") {
            continue;
        }
        let mut rest = l;
        while let Some(i) = rest.find("crate::") {
            let after = &rest[i + "crate::".len()..];
            let name: String = after
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            // `crate::{a, b}` lists several.
            if let Some(list) = after.strip_prefix('{') {
                let inner = list.split('}').next().unwrap_or("");
                for part in inner.split(',') {
                    let m: String = part
                        .trim()
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                        .collect();
                    if !m.is_empty() {
                        found.insert(m);
                    }
                }
            } else if !name.is_empty() {
                found.insert(name);
            }
            rest = after;
        }
    }
    found
}

/// Module -> modules it imports, for one crate's `src/`.
fn graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            if p.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let Some(m) = module_of(p.strip_prefix(src).unwrap()) else {
                continue;
            };
            let text = std::fs::read_to_string(&p).unwrap();
            let entry = g.entry(m.clone()).or_default();
            for i in imports(&text) {
                if i != m {
                    entry.insert(i);
                }
            }
        }
    }
    g
}

/// A circle of imports, if there is one.
fn circle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(i) = path.iter().position(|p| p == n) {
            let mut c = path[i..].to_vec();
            c.push(n.to_string());
            return Some(c);
        }
        if done.contains(n) {
            return None;
        }
        path.push(n.to_string());
        for next in g.get(n).into_iter().flatten() {
            if let Some(c) = visit(next, g, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    g.keys()
        .find_map(|n| visit(n, g, &mut Vec::new(), &mut done))
}

#[test]
fn no_crate_has_an_import_circle() {
    for krate in ["shared", "ppmd", "udp-ingress", "tools", "tests"] {
        let g = graph(&Path::new(ROOT).join(krate).join("src"));
        if let Some(c) = circle(&g) {
            panic!(
                "{krate}: modules import each other in a circle: {}",
                c.join(" -> ")
            );
        }
    }
}

#[test]
fn the_circle_finder_finds_circles() {
    let g: BTreeMap<String, BTreeSet<String>> = [
        ("a", vec!["b"]),
        ("b", vec!["c"]),
        ("c", vec!["a"]),
        ("d", vec!["a"]),
    ]
    .into_iter()
    .map(|(k, v)| (k.into(), v.into_iter().map(String::from).collect()))
    .collect();
    assert_eq!(circle(&g).unwrap(), ["a", "b", "c", "a"]);
    let mut acyclic = g.clone();
    acyclic.get_mut("c").unwrap().clear();
    assert_eq!(circle(&acyclic), None);
    assert_eq!(
        imports("use crate::frame::{Level, X};\nuse crate::{config, receiver::R};\n// crate::gone\n#[cfg(test)]\nuse crate::late;"),
        ["config", "frame", "receiver"].into_iter().map(String::from).collect()
    );
    // Tests out of line: the code after `mod tests;` is read, the test
    // module's own file is not.
    assert_eq!(
        imports("use crate::a;\n#[cfg(test)]\nmod tests;\npub use crate::b;\n#[cfg(test)]\nmod inline {\n    use crate::c;\n}"),
        ["a", "b"].into_iter().map(String::from).collect()
    );
    assert_eq!(module_of(Path::new("config/tests/units.rs")), None);
    assert_eq!(module_of(Path::new("frame/tests.rs")), None);
    assert_eq!(module_of(Path::new("tests.rs")), None);
    assert_eq!(
        module_of(Path::new("config/plan.rs")).as_deref(),
        Some("config")
    );
}
