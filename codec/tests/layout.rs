//! The layout rules of issues 28 and 57, checked on the sources: no module of any crate imports
//! one that imports it back (library code and unit tests alike; paths through `crate::`,
//! `self::`, `super::`, grouped use trees and a parent's bare child paths, resolved as the
//! compiler resolves them), no file of any crate over 600 lines, and no
//! function over 120 lines outside tests except those listed in `LONG_FUNCTIONS`, each with why
//! it stays whole.
//!
//! Hand-written rather than `cargo modules dependencies --acyclic`: that tool builds
//! rust-analyzer (minutes of CI for one check) and its output changes with its versions; the
//! few path forms of our sources are parsed here, and the checker's own test writes a tree with
//! a circle in each form and sees it found. One form it does not resolve: a module that
//! glob-imports the crate root (`use crate::*`) and then names a sibling bare (`batch::X`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).expect("source folder") {
        let p = e.expect("entry").path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The crates whose modules must not import each other in a circle, by source folder.
const CRATES: &[&str] = &[
    "proto/src",
    "codec/src",
    "gpu/src",
    "server/src",
    "cli/src",
    "python/src",
    "client/src",
    "wasm/src",
];

/// `core/decode.rs` -> `core::decode`; `codecs/fis/mod.rs` -> `codecs::fis`; `lib.rs` and
/// `main.rs` -> `` (the crate root).
fn module_of(src: &Path, file: &Path) -> String {
    let rel = file
        .strip_prefix(src)
        .expect("under src")
        .with_extension("");
    let mut parts: Vec<String> = rel
        .iter()
        .map(|s| s.to_string_lossy().into_owned())
        .collect();
    let root_file = parts.len() == 1 && matches!(parts[0].as_str(), "lib" | "main");
    if root_file || parts.last().map(String::as_str) == Some("mod") {
        parts.pop();
    }
    parts.join("::")
}

/// The text without comments (line, doc and block comments) and without the contents of string
/// and character literals, which may hold `::` of their own.
fn code_only(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'/' if b.get(i + 1) == Some(&b'/') => {
                while i < b.len() && b[i] != b'\n' {
                    i += 1;
                }
            }
            b'/' if b.get(i + 1) == Some(&b'*') => {
                let mut depth = 0;
                while i < b.len() {
                    if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
                        depth += 1;
                        i += 2;
                    } else if b[i] == b'*' && b.get(i + 1) == Some(&b'/') {
                        depth -= 1;
                        i += 2;
                        if depth == 0 {
                            break;
                        }
                    } else {
                        i += 1;
                    }
                }
            }
            b'"' => {
                // A raw string's hashes end it too; the few r#"..."# in the sources hold no
                // quote followed by a path, so a plain scan to the next unescaped quote does.
                out.push('"');
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
                out.push('"');
                i += 1;
            }
            b'\'' if b.get(i + 2) == Some(&b'\'') || b.get(i + 1) == Some(&b'\\') => {
                // A character literal ('x' or '\n'); lifetimes ('a) pass through.
                i += 1;
                while i < b.len() && b[i] != b'\'' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
                i += 1;
                out.push_str("' '");
            }
            c => {
                out.push(c as char);
                i += 1;
            }
        }
    }
    out
}

/// Tokens of code: identifiers, `::`, and single punctuation characters.
fn tokens(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    let b: Vec<char> = code.chars().collect();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c.is_alphanumeric() || c == '_' {
            let start = i;
            while i < b.len() && (b[i].is_alphanumeric() || b[i] == '_') {
                i += 1;
            }
            out.push(b[start..i].iter().collect());
        } else if c == ':' && b.get(i + 1) == Some(&':') {
            out.push("::".into());
            i += 2;
        } else {
            if !c.is_whitespace() {
                out.push(c.to_string());
            }
            i += 1;
        }
    }
    out
}

/// The paths of a use tree or path expression starting at `tokens[at]`: `a::b::{c, d::{e,
/// self}}` gives `a::b::c`, `a::b::d::e` and `a::b::d`. Returns them and the index after.
fn paths_at(tokens: &[String], at: usize) -> (Vec<Vec<String>>, usize) {
    let mut prefix = Vec::new();
    let mut i = at;
    loop {
        match tokens.get(i).map(String::as_str) {
            Some("{") => {
                let mut out = Vec::new();
                i += 1;
                while i < tokens.len() && tokens[i] != "}" {
                    if tokens[i] == "," {
                        i += 1;
                        continue;
                    }
                    let (inner, next) = paths_at(tokens, i);
                    for p in inner {
                        let mut full = prefix.clone();
                        full.extend(p.into_iter().filter(|s| s != "self"));
                        out.push(full);
                    }
                    // Skip what the inner path did not take (`as name`, `*`).
                    i = next.max(i + 1);
                    while i < tokens.len() && tokens[i] != "," && tokens[i] != "}" {
                        i += 1;
                    }
                }
                return (out, i + 1);
            }
            Some(t) if t.chars().all(|c| c.is_alphanumeric() || c == '_') => {
                prefix.push(t.to_string());
                i += 1;
                if tokens.get(i).map(String::as_str) == Some("::") {
                    i += 1;
                } else {
                    return (vec![prefix], i);
                }
            }
            _ => return (vec![prefix], i),
        }
    }
}

/// A path a file names: the module it reaches, the name after that module (an item, if any),
/// and whether it is re-exported there (`pub use`).
struct Named {
    module: String,
    item: Option<String>,
    reexport: bool,
}

/// The paths a file of module `module` names, resolved against the crate's `modules`:
/// `crate::`, `self::` and `super::` paths (repeated `super` too), grouped use trees, and paths
/// that start with a child module the file declares (`mod child;` then `child::item`).
/// Inline modules (`mod tests { .. }`) count as their file's module: a unit test's imports are
/// its module's.
fn paths_named(module: &str, text: &str, modules: &BTreeSet<String>) -> Vec<Named> {
    let code = code_only(text);
    let toks = tokens(&code);
    let join = |base: &str, seg: &str| {
        if base.is_empty() {
            seg.to_string()
        } else {
            format!("{base}::{seg}")
        }
    };
    // Children declared by this file (`mod name;`), which its bare paths may start with.
    let children: BTreeSet<String> = toks
        .windows(3)
        .filter(|w| w[0] == "mod" && w[2] == ";")
        .map(|w| w[1].clone())
        .collect();
    let mut out = Vec::new();
    // Inline modules open at these brace depths: `super` leaves them before the file's module.
    let (mut depth, mut inline) = (0usize, Vec::new());
    let mut i = 0;
    while i < toks.len() {
        let t = toks[i].as_str();
        match t {
            "{" => depth += 1,
            "}" => {
                if inline.last() == Some(&depth) {
                    inline.pop();
                }
                depth = depth.saturating_sub(1);
            }
            "mod" if toks.get(i + 2).map(String::as_str) == Some("{") => {
                inline.push(depth + 1);
            }
            _ => {}
        }
        let after_path = i > 0 && (toks[i - 1] == "::" || toks[i - 1] == "mod");
        let anchored = matches!(t, "crate" | "self" | "super") || children.contains(t);
        if after_path || !anchored || toks.get(i + 1).map(String::as_str) != Some("::") {
            i += 1;
            continue;
        }
        // `pub use`, `pub(crate) use`, `pub(super) use`.
        let reexport = i >= 2
            && toks[i - 1] == "use"
            && (toks[i - 2] == "pub" || (toks[i - 2] == ")" && i >= 5 && toks[i - 5] == "pub"));
        let (paths, next) = paths_at(&toks, i);
        for p in paths {
            let mut segs = p.iter().map(String::as_str).peekable();
            let mut at = match segs.peek().copied() {
                Some("crate") => {
                    segs.next();
                    String::new()
                }
                _ => module.to_string(),
            };
            let mut nested = inline.len();
            while let Some(&s) = segs.peek() {
                match s {
                    "self" => {}
                    "super" if nested > 0 => nested -= 1,
                    "super" => {
                        at = at
                            .rsplit_once("::")
                            .map_or(String::new(), |(a, _)| a.into());
                    }
                    _ => break,
                }
                segs.next();
            }
            let mut item = None;
            for s in segs {
                let deeper = join(&at, s);
                if !modules.contains(&deeper) {
                    item = Some(s.to_string());
                    break;
                }
                at = deeper;
            }
            out.push(Named {
                module: at,
                item,
                reexport,
            });
        }
        i = next.max(i + 1);
    }
    out
}

/// The import graph of `texts` (module -> source): each module and the modules it names,
/// through re-exports to where the item is (`crate::Raster` names `io::raster` when the root
/// has `pub use io::raster::Raster`). The crate root is left out: it declares every module and
/// re-exports their items (a facade), so a path to one of its own items (`crate::Error`) would
/// close a circle through it. Likewise a module's `pub use` of its own descendants' items.
fn import_graph(texts: &BTreeMap<String, String>) -> BTreeMap<String, BTreeSet<String>> {
    let modules: BTreeSet<String> = texts.keys().cloned().collect();
    let named: BTreeMap<&String, Vec<Named>> = texts
        .iter()
        .map(|(m, t)| (m, paths_named(m, t, &modules)))
        .collect();
    // Each module's re-exported names, and the module each comes from.
    // Globs (`pub use model::*`) by module: a name they bring is found where it is defined.
    let mut reexports: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    let mut globs: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (m, paths) in &named {
        for p in paths.iter().filter(|p| p.reexport) {
            match &p.item {
                Some(item) => {
                    reexports
                        .entry((*m).clone())
                        .or_default()
                        .insert(item.clone(), p.module.clone());
                }
                None => globs
                    .entry((*m).clone())
                    .or_default()
                    .push(p.module.clone()),
            }
        }
    }
    let defines = |module: &str, item: &str| {
        let toks = tokens(&code_only(&texts[module]));
        toks.windows(2).any(|w| {
            w[1] == item
                && matches!(
                    w[0].as_str(),
                    "fn" | "struct" | "enum" | "trait" | "type" | "const" | "static" | "union"
                )
        })
    };
    let resolve = |p: &Named| {
        let mut at = p.module.clone();
        let Some(item) = &p.item else { return at };
        // A re-export of a re-export, a few deep at most.
        for _ in 0..4 {
            let named = reexports.get(&at).and_then(|r| r.get(item));
            let globbed = || {
                globs
                    .get(&at)?
                    .iter()
                    .find(|g| texts.contains_key(*g) && defines(g, item))
            };
            match named.or_else(globbed) {
                Some(to) if *to != at => at = to.clone(),
                _ => break,
            }
        }
        at
    };
    named
        .iter()
        .filter(|(m, _)| !m.is_empty())
        .map(|(m, paths)| {
            // A module that publishes its own children's items (`pub use operator::ProjectedOperator`
            // in `codecs/projected/mod.rs`) is their facade, as the root is everyone's: that edge is
            // not a dependence, and the child may use its parent's items.
            let below = format!("{m}::");
            let mut deps: BTreeSet<String> = paths
                .iter()
                .filter(|p| !(p.reexport && resolve(p).starts_with(&below)))
                .map(resolve)
                .collect();
            deps.remove(*m);
            deps.remove("");
            ((*m).clone(), deps)
        })
        .collect()
}

/// The import circles among `texts`: every group of modules that reach each other (a strongly
/// connected component of more than one module), each as one path around it.
fn import_circles(texts: &BTreeMap<String, String>) -> Vec<Vec<String>> {
    let graph = import_graph(texts);
    let reach = |from: &String| -> BTreeSet<String> {
        let mut seen = BTreeSet::new();
        let mut stack = vec![from.clone()];
        while let Some(m) = stack.pop() {
            for d in graph.get(&m).into_iter().flatten() {
                if seen.insert(d.clone()) {
                    stack.push(d.clone());
                }
            }
        }
        seen
    };
    let reached: BTreeMap<&String, BTreeSet<String>> =
        graph.keys().map(|m| (m, reach(m))).collect();
    let mut done = BTreeSet::new();
    let mut circles = Vec::new();
    for (m, r) in &reached {
        if done.contains(*m) || !r.contains(*m) {
            continue;
        }
        // The component: the modules m reaches that reach m back.
        let component: BTreeSet<&String> = r
            .iter()
            .filter(|d| reached.get(d).is_some_and(|back| back.contains(*m)))
            .collect();
        done.extend(component.iter().map(|d| (*d).clone()));
        // One path around it: from m, a shortest walk back to m inside the component.
        let mut from: BTreeMap<String, String> = BTreeMap::new();
        let mut queue = std::collections::VecDeque::from([(*m).clone()]);
        'search: while let Some(x) = queue.pop_front() {
            for d in &graph[&x] {
                if d == *m {
                    from.insert(format!("{m}#end"), x.clone());
                    break 'search;
                }
                if component.contains(d) && !from.contains_key(d) {
                    from.insert(d.clone(), x.clone());
                    queue.push_back(d.clone());
                }
            }
        }
        let mut path = vec![(*m).clone()];
        let mut at = from[&format!("{m}#end")].clone();
        while &at != *m {
            path.push(at.clone());
            at = from[&at].clone();
        }
        path.push((*m).clone());
        path.reverse();
        circles.push(path);
    }
    circles
}

/// Each source file of the folder `src` by module.
fn crate_texts(src: &Path) -> BTreeMap<String, String> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    files
        .iter()
        .map(|f| {
            (
                module_of(src, f),
                std::fs::read_to_string(f).expect("readable"),
            )
        })
        .collect()
}

#[test]
fn no_module_of_any_crate_imports_one_that_imports_it_back() {
    let mut circles = Vec::new();
    for dir in CRATES {
        let texts = crate_texts(&root().join(dir));
        assert!(texts.len() > 1, "{dir}: no modules found");
        for path in import_circles(&texts) {
            circles.push(format!("{dir}: {}", path.join(" -> ")));
        }
    }
    assert!(
        circles.is_empty(),
        "import circles:\n{}",
        circles.join("\n")
    );
}

#[test]
fn the_checker_sees_circles_written_every_way_a_path_can_be() {
    // A real tree on disk, read as the crates are: lib.rs declares a, b and p; p declares c.
    let dir = std::env::temp_dir().join(format!("fractile-layout-{}", std::process::id()));
    let write = |files: &[(&str, &str)]| {
        let _ = std::fs::remove_dir_all(&dir);
        for (name, text) in files {
            let path = dir.join(name);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, text).unwrap();
        }
        crate_texts(&dir)
    };
    let lib = ("lib.rs", "mod a;\nmod b;\nmod p;\nmod q;\npub use a::A;\n");
    let q = ("q.rs", "pub use crate::a::*;\n");
    let p = ("p/mod.rs", "mod c;\npub struct P;\n");
    let c = ("p/c.rs", "pub struct C;\n");
    // No circle: a -> b, b -> p::c.
    let clean = write(&[
        lib,
        p,
        c,
        ("a.rs", "use crate::b::B;\npub struct A;\n"),
        ("b.rs", "use crate::p::c::C;\npub struct B(C);\n"),
    ]);
    assert!(import_circles(&clean).is_empty());
    // Each way of writing the path that closes a -> b -> a.
    for (how, b_text) in [
        ("crate::", "use crate::a::A;\n"),
        ("super::", "use super::a::A;\n"),
        ("a grouped use", "use crate::{p::P, a::{self, A}};\n"),
        (
            "a multi-line group",
            "use crate::{\n    p::P,\n    a::A,\n};\n",
        ),
        (
            "a path in code",
            "fn f() -> usize { std::mem::size_of::<super::a::A>() }\n",
        ),
        ("the root's re-export", "use crate::A;\n"),
        ("a glob re-export", "use crate::q::A2;\n"),
    ] {
        let texts = write(&[
            lib,
            p,
            c,
            q,
            ("a.rs", "use crate::b::B;\npub struct A;\npub struct A2;\n"),
            ("b.rs", b_text),
        ]);
        assert!(!import_circles(&texts).is_empty(), "missed through {how}");
    }
    // A parent's bare child path and the child's `super::` back: p -> p::c -> p.
    let texts = write(&[
        lib,
        (
            "p/mod.rs",
            "mod c;\npub struct P;\nfn f() -> c::C { c::C }\n",
        ),
        ("p/c.rs", "use super::P;\npub struct C;\n"),
    ]);
    assert_eq!(
        import_circles(&texts),
        vec![vec!["p".to_string(), "p::c".into(), "p".into()]]
    );
    // A name a parent re-exports by a glob is found where it is defined: the child that names
    // it through the parent depends on the sibling, not on the parent (no circle).
    let texts = write(&[
        lib,
        (
            "p/mod.rs",
            "mod c;\nmod d;\npub use d::*;\nfn f() -> c::C { c::C }\n",
        ),
        ("p/c.rs", "use crate::p::D;\npub struct C(D);\n"),
        ("p/d.rs", "pub struct D;\n"),
    ]);
    assert!(import_circles(&texts).is_empty());
    // Comments, strings and unit tests' own modules: a unit test's imports count; a comment's
    // and a string's do not.
    let texts = write(&[
        lib,
        p,
        c,
        ("a.rs", "use crate::b::B;\n// crate::b in a comment\n"),
        (
            "b.rs",
            "const S: &str = \"crate::a::A\";\n/* crate::a::A */\n#[cfg(test)]\nmod tests {\n    use super::*;\n    use super::super::p::P;\n}\n",
        ),
    ]);
    assert!(import_circles(&texts).is_empty());
    let texts = write(&[
        lib,
        p,
        c,
        ("a.rs", "use crate::b::B;\n"),
        (
            "b.rs",
            "#[cfg(test)]\nmod tests {\n    use crate::a::A;\n}\n",
        ),
    ]);
    assert!(!import_circles(&texts).is_empty(), "a unit test's import");
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 57 split the seventeen files of the codec, the GPU and the client that were over
/// (ARCHITECTURE.md names the modules they became).
#[test]
fn no_file_of_any_crate_is_over_600_lines() {
    let mut over = Vec::new();
    for dir in CRATES {
        let mut files = Vec::new();
        rust_files(&root().join(dir), &mut files);
        assert!(!files.is_empty(), "{dir}");
        for f in files {
            let n = std::fs::read_to_string(&f)
                .expect("readable")
                .lines()
                .count();
            if n > 600 {
                over.push(format!("{}: {n} lines", f.display()));
            }
        }
    }
    assert!(over.is_empty(), "{over:#?}");
}

/// Functions over 120 lines that stay whole, and why.
const LONG_FUNCTIONS: &[(&str, &str, &str)] = &[
    (
        "codec/src/core/decode/continuous.rs",
        "grid",
        "continuous decoding's hot loop: one block work-list and the state it carries, in one \
         place so that its bit-for-bit agreement with point decoding (a property test) can be \
         read in one function",
    ),
    (
        "codec/src/core/decode/patch.rs",
        "patch",
        "the same hot loop in f64 for reprojected patches, kept beside `grid` line for line",
    ),
    (
        "codec/src/core/decode/discrete.rs",
        "discrete_volume",
        "the 3D discrete iteration, one loop nest that mirrors `discrete`",
    ),
    (
        "codec/src/codecs/curve/code.rs",
        "walk",
        "one walk of the stream shared by encoder and decoder (as the quadtree's): split, the two \
         directions could drift apart",
    ),
];

#[test]
fn no_function_is_over_120_lines_outside_tests() {
    let mut files = Vec::new();
    for dir in [
        "codec/src",
        "server/src",
        "cli/src",
        "python/src",
        "client/src",
        "gpu/src",
        "proto/src",
    ] {
        rust_files(&root().join(dir), &mut files);
    }
    let mut long = Vec::new();
    for f in &files {
        let text = std::fs::read_to_string(f).expect("readable");
        let lines: Vec<&str> = text.lines().collect();
        let end = lines
            .iter()
            .position(|l| l.starts_with("#[cfg(test)]"))
            .unwrap_or(lines.len());
        for (i, line) in lines[..end].iter().enumerate() {
            let code = line.trim_start();
            let indent = &line[..line.len() - code.len()];
            let signature = code
                .trim_start_matches("pub(crate) ")
                .trim_start_matches("pub(super) ")
                .trim_start_matches("pub ")
                .trim_start_matches("const ")
                .trim_start_matches("async ");
            let Some(name) = signature.strip_prefix("fn ") else {
                continue;
            };
            let name: String = name
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            // A declaration without a body (a trait's required method) ends in `;` before
            // any line opens a body.
            let opens = lines[i..]
                .iter()
                .map(|l| l.trim_end())
                .find(|l| l.ends_with('{') || l.ends_with(';'));
            if opens.is_none_or(|l| l.ends_with(';')) {
                continue;
            }
            // rustfmt closes a body with a brace at the signature's indentation.
            let close = format!("{indent}}}");
            let Some(len) = lines[i..].iter().position(|l| *l == close) else {
                continue;
            };
            if len + 1 > 120 {
                let rel = f
                    .strip_prefix(root())
                    .unwrap_or(f)
                    .to_string_lossy()
                    .replace("../", "");
                long.push((rel, name, len + 1));
            }
        }
    }
    let unexplained: Vec<_> = long
        .iter()
        .filter(|(f, n, _)| {
            !LONG_FUNCTIONS
                .iter()
                .any(|(lf, ln, _)| f.ends_with(lf) && n == ln)
        })
        .collect();
    assert!(
        unexplained.is_empty(),
        "functions over 120 lines: {unexplained:?}"
    );
}

/// The codec's modules marked `#[doc(hidden)]` (public only for the codec's own integration
/// tests and benches), as paths from the crate root: `codecs::quadtree::search`, ...
fn hidden_modules() -> BTreeSet<String> {
    let src = root().join("codec/src");
    let mut hidden = BTreeSet::new();
    for (module, text) in crate_texts(&src) {
        let lines: Vec<&str> = text.lines().map(str::trim).collect();
        for w in lines.windows(2) {
            let name = w[1]
                .strip_prefix("pub mod ")
                .and_then(|r| r.strip_suffix(';'));
            if let (true, Some(name)) = (w[0].starts_with("#[doc(hidden)]"), name) {
                let path = if module.is_empty() {
                    name.to_string()
                } else {
                    format!("{module}::{name}")
                };
                hidden.insert(path);
            }
        }
    }
    hidden
}

/// The codec paths a text names (`fractile_codec::a::b`, grouped trees expanded), each joined
/// by `::` without the crate name.
fn codec_paths(text: &str) -> Vec<String> {
    let t = tokens(&code_only(text));
    let mut out = Vec::new();
    for i in 0..t.len() {
        if t[i] == "fractile_codec" && t.get(i + 1).map(String::as_str) == Some("::") {
            let (paths, _) = paths_at(&t, i + 2);
            out.extend(paths.into_iter().map(|p| p.join("::")));
        }
    }
    out
}

/// The paths among `paths` that reach into a hidden module.
fn into_hidden(paths: &[String], hidden: &BTreeSet<String>) -> Vec<String> {
    paths
        .iter()
        .filter(|p| {
            hidden
                .iter()
                .any(|h| *p == h || p.starts_with(&format!("{h}::")))
        })
        .cloned()
        .collect()
}

/// Issue 57's curated API: the other crates (server, CLI, GPU, client, end-to-end tests, and
/// any crate added beside them) reach the codec through its public API only, never through a
/// module it keeps public for its own tests.
#[test]
fn no_other_crate_names_a_hidden_module_of_the_codec() {
    let hidden = hidden_modules();
    assert!(
        hidden.contains("codecs::quadtree::search"),
        "the hidden modules were not found: {hidden:?}"
    );
    let mut found = Vec::new();
    for e in std::fs::read_dir(root()).expect("workspace") {
        let dir = e.expect("entry").path();
        let name = dir.file_name().unwrap_or_default().to_string_lossy();
        if !dir.join("Cargo.toml").exists() || name == "codec" {
            continue;
        }
        let mut files = Vec::new();
        for sub in ["src", "tests", "benches", "examples"] {
            if dir.join(sub).is_dir() {
                rust_files(&dir.join(sub), &mut files);
            }
        }
        if dir.join("lib.rs").exists() {
            rust_files(&dir, &mut files);
        }
        for f in files {
            let text = std::fs::read_to_string(&f).expect("readable");
            for p in into_hidden(&codec_paths(&text), &hidden) {
                found.push(format!("{}: fractile_codec::{p}", f.display()));
            }
        }
    }
    found.sort();
    found.dedup();
    assert!(
        found.is_empty(),
        "hidden codec modules named:\n{}",
        found.join("\n")
    );
}

/// The check above sees a hidden module named directly and inside a grouped use tree, and
/// lets the public paths beside it pass.
#[test]
fn the_api_check_sees_hidden_modules_however_they_are_named() {
    let hidden: BTreeSet<String> = ["codecs::quadtree::search".to_string()].into();
    let text = "use fractile_codec::{Asset, codecs::{quadtree::{search::Fit, QuadtreeSettings}}};\n\
                fn f() { fractile_codec::codecs::quadtree::search::best(); }\n\
                // fractile_codec::codecs::quadtree::search in a comment is not code\n";
    let found = into_hidden(&codec_paths(text), &hidden);
    assert_eq!(
        found,
        vec![
            "codecs::quadtree::search::Fit".to_string(),
            "codecs::quadtree::search::best".to_string()
        ]
    );
}

/// The codec's layers, lowest first (ARCHITECTURE.md, "Layers"), as modules and the modules
/// under them (the longest that names a module places it): a module imports from its own
/// layer and those below it only, so that data flows one way, input -> encode -> asset ->
/// operator -> decode -> output, and a layer can be read without those above it. `io` holds
/// both the input (rasters, their masks, files written atomically, the frame of a file), which
/// the codecs read and size their files with, and the asset container, which holds the
/// codecs' payloads.
const LAYERS: [&[&str]; 5] = [
    &["core"],
    &[
        "geo",
        "mesh",
        "render",
        "io::raster",
        "io::mask",
        "io::atomic",
        "io::frame",
    ],
    &["codecs"],
    &["io"],
    &["encode", "extract"],
];

fn layer_of(module: &str) -> Option<usize> {
    let under = |m: &str| module == m || module.starts_with(&format!("{m}::"));
    (0..LAYERS.len())
        .flat_map(|k| {
            LAYERS[k]
                .iter()
                .filter(|m| under(m))
                .map(move |m| (m.len(), k))
        })
        .max()
        .map(|(_, k)| k)
}

/// Each import of the codec crate from a module of a lower layer to one of a higher.
fn upward_imports(texts: &BTreeMap<String, String>) -> BTreeSet<(String, String)> {
    let mut up = BTreeSet::new();
    for (m, deps) in import_graph(texts) {
        let Some(from) = layer_of(&m) else { continue };
        for d in deps {
            if layer_of(&d).is_some_and(|to| to > from) {
                up.insert((m.clone(), d));
            }
        }
    }
    up
}

#[test]
fn imports_run_down_the_layers() {
    let texts = crate_texts(&root().join("codec/src"));
    let tops: BTreeSet<&str> = texts
        .keys()
        .filter_map(|m| m.split("::").next())
        .filter(|t| !t.is_empty())
        .collect();
    for top in &tops {
        assert!(layer_of(top).is_some(), "{top}: in no layer of LAYERS");
    }
    let up = upward_imports(&texts);
    assert!(up.is_empty(), "imports up the layers:\n{up:#?}");
}

/// The plane codecs' folders and types, as the registry lists them (`plane_codecs!` in
/// `codecs/mod.rs`: `Name(crate::codecs::<folder>::..::Header, ..::Settings)`).
fn registered_codecs() -> (BTreeSet<String>, BTreeSet<String>) {
    let text = std::fs::read_to_string(root().join("codec/src/codecs/mod.rs")).expect("registry");
    let start = text
        .find("macro_rules! plane_codecs")
        .expect("plane_codecs!");
    let list = &text[start..start + text[start..].find("\n}\n").expect("its end")];
    let (mut folders, mut types) = (BTreeSet::new(), BTreeSet::new());
    for path in list.split("crate::codecs::").skip(1) {
        let path: String = path
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
            .collect();
        let segments: Vec<&str> = path.split("::").collect();
        folders.insert(segments[0].to_string());
        types.insert(segments[segments.len() - 1].to_string());
    }
    (folders, types)
}

/// A new plane codec needs no edit outside its folder and its lines in the registry
/// (`tests/new_codec.sh` adds one and runs the CLI, the server and Python on it): no source of
/// another crate names a plane codec's header or settings, or reaches into a codec's folder,
/// but for the name of the codec a default picks (`CODEC_NAME`); the command line and Python
/// reach the codecs by name through `CodecSettings::named`.
#[test]
fn no_other_crate_names_a_plane_codec() {
    let (folders, types) = registered_codecs();
    assert!(
        folders.len() >= 4 && types.len() >= 8,
        "{folders:?} {types:?}"
    );
    let mut named = Vec::new();
    for krate in [
        "cli", "server", "client", "python", "wasm", "gpu", "remote", "proto",
    ] {
        let mut files = Vec::new();
        rust_files(&root().join(krate).join("src"), &mut files);
        for f in files {
            let text = std::fs::read_to_string(&f).expect("source");
            for (n, line) in text.lines().enumerate() {
                let code = line.split("//").next().unwrap_or("");
                let word = |w: &str| {
                    code.match_indices(w).any(|(i, _)| {
                        let before = code[..i].chars().next_back();
                        let after = code[i + w.len()..].chars().next();
                        let edge =
                            |c: Option<char>| !c.is_some_and(|c| c.is_alphanumeric() || c == '_');
                        edge(before) && edge(after)
                    })
                };
                let reaches = folders.iter().any(|m| {
                    let at = format!("codecs::{m}::");
                    code.match_indices(&at)
                        .any(|(i, _)| !code[i + at.len()..].starts_with("CODEC_NAME"))
                });
                if reaches || types.iter().any(|t| word(t)) {
                    named.push(format!("{}:{}: {}", f.display(), n + 1, line.trim()));
                }
            }
        }
    }
    assert!(
        named.is_empty(),
        "sources outside the codec crate that name a plane codec:\n{}",
        named.join("\n")
    );
}

/// Each codec's errors are typed (issue 76): no function of the codec answers a bare `String`
/// as its error (`core::format::FormatError` for coded bytes, `crate::Error` for the rest), so
/// that a caller tells a bad header from a bad stream, or the input's fault from the file's,
/// without reading a message.
#[test]
fn no_codec_function_answers_a_string_error() {
    let found: Vec<String> = crate_texts(&root().join("codec/src"))
        .iter()
        .flat_map(|(m, text)| {
            text.lines()
                .enumerate()
                .filter(|(_, l)| {
                    let code = l.split("//").next().unwrap_or("");
                    code.contains("Result<") && code.contains(", String>")
                })
                .map(move |(n, l)| format!("{m}:{}: {}", n + 1, l.trim()))
        })
        .collect();
    assert!(found.is_empty(), "string errors:\n{}", found.join("\n"));
}

/// The codec's and the server's surfaces are curated: the modules under them are private, and
/// what other crates name is re-exported by concept at the root (`codec/src/lib.rs`,
/// `server/src/lib.rs`). A module made public again exposes its every `pub` item.
#[test]
fn the_crates_publish_a_curated_surface() {
    let declared = |lib: &str, module: &str| -> Option<String> {
        let text = std::fs::read_to_string(root().join(lib)).expect("lib.rs");
        text.lines()
            .map(str::trim)
            .find(|l| l.ends_with(&format!("mod {module};")))
            .map(str::to_string)
    };
    let private = [
        ("codec/src/lib.rs", &["core", "io"][..]),
        (
            "server/src/lib.rs",
            &[
                "api",
                "backend",
                "error",
                "memory",
                "openapi",
                "store",
                "telemetry",
                "web",
                "work",
            ][..],
        ),
    ];
    for (lib, modules) in private {
        for m in modules {
            let line = declared(lib, m).unwrap_or_else(|| panic!("{lib}: no `mod {m};`"));
            assert_eq!(line, format!("mod {m};"), "{lib}: {m} is to stay private");
        }
    }
}
