//! The house rules of the workspace, checked on its own sources: no import circle between the
//! files of a crate, no shipped file over 450 non-blank lines and no shipped function over 80
//! lines (test modules, `tests.rs` files, `tests/` and `benches/` are free).
//!
//! An import is any `use` or path of a file that names another file's module: `crate::a::b`,
//! `super::x` (also inside `{...}` groups) and, in a module with children, `use child::...`.
//! `$crate::` in macro bodies names the crate for the macro's user and is no import.
#![allow(clippy::unwrap_used, reason = "test helpers: a failure is a failed test")]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const MAX_FILE_LINES: usize = 450;
const MAX_FN_LINES: usize = 80;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every `src/` folder of a crate (holding `lib.rs` or `main.rs`) under the shipped top folders.
fn crate_roots() -> Vec<PathBuf> {
    let mut roots = Vec::new();
    for top in ["framework", "plugins", "apps"] {
        walk(&workspace().join(top), &mut |p| {
            if p.file_name().is_some_and(|n| n == "lib.rs" || n == "main.rs") && p.parent().is_some_and(|d| d.ends_with("src")) {
                roots.push(p.parent().unwrap().to_path_buf());
            }
        });
    }
    roots.sort();
    roots
}

fn walk(dir: &Path, f: &mut dyn FnMut(&Path)) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut entries: Vec<_> = entries.flatten().map(|e| e.path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            if !p.ends_with("target") && !p.ends_with("tests") {
                walk(&p, f);
            }
        } else {
            f(&p);
        }
    }
}

fn is_test_file(p: &Path) -> bool {
    let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
    name == "tests.rs" || name.ends_with("_tests.rs")
}

/// A file's shipped lines: everything before its first `#[cfg(test)]`.
fn shipped(text: &str) -> Vec<&str> {
    text.lines().take_while(|l| !l.trim().starts_with("#[cfg(test)]")).collect()
}

/// The module path of a file below its crate's `src/`.
fn module_path(root: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(root).unwrap().with_extension("");
    let mut parts: Vec<String> = rel.iter().map(|s| s.to_string_lossy().into_owned()).collect();
    if parts.last().is_some_and(|l| l == "lib" || l == "main" || l == "mod") {
        parts.pop();
    }
    parts
}

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// The paths that follow `at` in `code` (`a::b::c`, or `a::{b, c::d}` as `a::b` and `a::c`).
fn paths_after(code: &str, at: usize) -> Vec<Vec<String>> {
    let mut prefix = Vec::new();
    let mut rest = &code[at..];
    loop {
        let ident: String = rest.chars().take_while(|c| is_ident(*c)).collect();
        if ident.is_empty() {
            break;
        }
        rest = &rest[ident.len()..];
        prefix.push(ident);
        if let Some(r) = rest.strip_prefix("::") {
            rest = r;
        } else {
            return vec![prefix];
        }
    }
    if let Some(group) = rest.strip_prefix('{') {
        let mut depth = 1;
        let end = group
            .char_indices()
            .find(|&(_, c)| {
                depth += i32::from(c == '{') - i32::from(c == '}');
                depth == 0
            })
            .map_or(group.len(), |(i, _)| i);
        let mut out = Vec::new();
        let mut item_depth = 0;
        let mut start = 0;
        for (i, c) in group[..end].char_indices().chain([(end, ',')]) {
            item_depth += i32::from(c == '{') - i32::from(c == '}');
            if c == ',' && item_depth == 0 {
                let first: String = group[start..i].trim().chars().take_while(|c| is_ident(*c)).collect();
                let mut p = prefix.clone();
                if !first.is_empty() && first != "self" {
                    p.push(first);
                }
                out.push(p);
                start = i + 1;
            }
        }
        return out;
    }
    vec![prefix]
}

/// The module paths a file's shipped code refers to.
fn references(module: &[String], is_dir_module: bool, code: &str) -> Vec<Vec<String>> {
    let mut refs = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let before = code[..i].chars().next_back();
        if before.is_some_and(|c| c == '$' || is_ident(c)) {
            continue;
        }
        refs.extend(paths_after(code, i + "crate::".len()));
    }
    for (i, _) in code.match_indices("super::") {
        if code[..i].ends_with("super::") || code[..i].chars().next_back().is_some_and(is_ident) {
            continue;
        }
        let mut n = 0;
        let mut at = i;
        while code[at..].starts_with("super::") {
            n += 1;
            at += "super::".len();
        }
        let base = &module[..module.len().saturating_sub(n)];
        refs.extend(paths_after(code, at).into_iter().map(|p| base.iter().cloned().chain(p).collect()));
    }
    if is_dir_module {
        for line in code.lines() {
            let l = line.trim_start();
            let l = l.strip_prefix("pub ").or_else(|| l.strip_prefix("pub(crate) ")).unwrap_or(l);
            if let Some(rest) = l.strip_prefix("use ") {
                let first: String = rest.chars().take_while(|c| is_ident(*c)).collect();
                if !["crate", "super", "self", "std", "core", "alloc"].contains(&first.as_str()) && rest[first.len()..].starts_with("::") {
                    let start = line.len() - rest.len();
                    refs.extend(paths_after(line, start).into_iter().map(|p| module.iter().cloned().chain(p).collect()));
                }
            }
        }
    }
    refs
}

/// Strongly connected components of more than one file (Tarjan).
fn cycles(edges: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>) -> Vec<Vec<Vec<String>>> {
    struct T<'a> {
        edges: &'a BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        index: BTreeMap<&'a Vec<String>, usize>,
        low: BTreeMap<&'a Vec<String>, usize>,
        stack: Vec<&'a Vec<String>>,
        out: Vec<Vec<Vec<String>>>,
    }
    fn visit<'a>(t: &mut T<'a>, v: &'a Vec<String>) {
        let i = t.index.len();
        t.index.insert(v, i);
        t.low.insert(v, i);
        t.stack.push(v);
        for w in &t.edges[v] {
            if !t.index.contains_key(w) {
                visit(t, w);
                let lw = t.low[w];
                let lv = t.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if t.stack.contains(&w) {
                let iw = t.index[w];
                let lv = t.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if t.low[v] == t.index[v] {
            let mut comp = Vec::new();
            while let Some(w) = t.stack.pop() {
                comp.push(w.clone());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                t.out.push(comp);
            }
        }
    }
    let mut t = T { edges, index: BTreeMap::new(), low: BTreeMap::new(), stack: Vec::new(), out: Vec::new() };
    for v in edges.keys() {
        if !t.index.contains_key(v) {
            visit(&mut t, v);
        }
    }
    t.out
}

#[test]
fn no_import_circle_between_the_files_of_any_crate() {
    let roots = crate_roots();
    assert!(roots.len() >= 10, "found only {} crates: {roots:?}", roots.len());
    let mut found = Vec::new();
    for root in &roots {
        let mut files = BTreeMap::new();
        walk(root, &mut |p| {
            if p.extension().is_some_and(|e| e == "rs") && !is_test_file(p) {
                files.insert(module_path(root, p), p.to_path_buf());
            }
        });
        let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = files.keys().map(|m| (m.clone(), BTreeSet::new())).collect();
        for (module, path) in &files {
            let text = std::fs::read_to_string(path).unwrap();
            let code: String = shipped(&text).iter().map(|l| l.split("//").next().unwrap_or("")).collect::<Vec<_>>().join("\n");
            let dir_module = path.file_name().is_some_and(|n| n == "mod.rs" || n == "lib.rs" || n == "main.rs");
            for r in references(module, dir_module, &code) {
                let target = (0..=r.len()).rev().map(|k| r[..k].to_vec()).find(|p| files.contains_key(p));
                if let Some(t) = target.filter(|t| t != module) {
                    edges.get_mut(module).unwrap().insert(t);
                }
            }
        }
        for comp in cycles(&edges) {
            found.push(format!(
                "{}: {:?}",
                root.display(),
                comp.iter().map(|m| files[m].strip_prefix(root).unwrap().display().to_string()).collect::<Vec<_>>()
            ));
        }
    }
    assert!(found.is_empty(), "import circles between files:\n{}", found.join("\n"));
}

#[test]
fn the_checker_sees_a_circle_through_a_group_import() {
    let mut edges = BTreeMap::new();
    let (a, b) = (vec!["a".to_string()], vec!["a".to_string(), "b".to_string()]);
    let refs_a = references(&a, true, "use b::Thing;\n");
    let refs_b = references(&b, false, "use super::{Other, b2};\nlet x = $crate::c::D;\n");
    assert_eq!(refs_a, vec![vec!["a".to_string(), "b".to_string(), "Thing".to_string()]]);
    assert_eq!(refs_b, vec![vec!["a".to_string(), "Other".to_string()], vec!["a".to_string(), "b2".to_string()]]);
    edges.insert(a.clone(), BTreeSet::from([b.clone()]));
    edges.insert(b.clone(), BTreeSet::from([a.clone()]));
    assert_eq!(cycles(&edges).len(), 1);
}

#[test]
fn no_shipped_file_or_function_is_too_long() {
    let mut long = Vec::new();
    for root in crate_roots() {
        walk(&root, &mut |p| {
            let is_code = p.extension().is_some_and(|e| e == "rs" || e == "wgsl");
            if !is_code || is_test_file(p) {
                return;
            }
            let text = std::fs::read_to_string(p).unwrap();
            let lines = shipped(&text);
            let non_blank = lines.iter().filter(|l| !l.trim().is_empty()).count();
            if non_blank > MAX_FILE_LINES {
                long.push(format!("{} ({non_blank} non-blank lines)", p.display()));
            }
            for (i, l) in lines.iter().enumerate() {
                let t = l.trim_start();
                let indent = &l[..l.len() - t.len()];
                let signature = [
                    "pub(crate) fn ",
                    "pub(super) fn ",
                    "pub fn ",
                    "fn ",
                    "pub const fn ",
                    "const fn ",
                    "pub unsafe fn ",
                    "unsafe fn ",
                    "pub extern \"C\" fn ",
                    "extern \"C\" fn ",
                ];
                if !signature.iter().any(|s| t.starts_with(s)) || l.trim_end().ends_with(';') {
                    continue;
                }
                let close = format!("{indent}}}");
                if let Some(j) = lines[i + 1..].iter().position(|m| m.starts_with(&close) && !m.starts_with(&format!("{indent} ")))
                    && j + 2 > MAX_FN_LINES
                {
                    long.push(format!("{}:{} ({} lines)", p.display(), i + 1, j + 2));
                }
            }
        });
    }
    assert!(long.is_empty(), "over {MAX_FILE_LINES} non-blank lines a file or {MAX_FN_LINES} lines a function:\n{}", long.join("\n"));
}
