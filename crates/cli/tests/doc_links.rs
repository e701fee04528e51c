//! The README as a front page and the documentation's links (issue 71): every relative link in README.md and
//! docs/**/*.md (`[text](path)`, `[text](path#anchor)`, `[text](#anchor)`, images, `[label]: path` definitions)
//! names a file or folder that exists, and an anchor into a Markdown file names one of its headings (GitHub's
//! slugs: lowercase, spaces to '-', punctuation other than '-' and '_' dropped, repeats numbered `-1`, `-2`, …).
//! Links inside fenced code blocks and code spans are text, not links. The README stays under 10 KB and keeps the
//! two fresh-machine commands as its first and second fenced code blocks (checks read them by position).

use std::collections::HashSet;
use std::path::{Component, Path, PathBuf};

const README_MAX_BYTES: usize = 10240;
const DEMO_COMMAND: &str = "cargo run --release -p mvsplat360-cli -- demo";
const TEST_COMMAND: &str = "scripts/test";

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A fence line's character and length (``` or ~~~, at most 3 spaces in).
fn fence(line: &str) -> Option<(char, usize)> {
    let t = line.trim_start_matches(' ');
    if line.len() - t.len() > 3 {
        return None;
    }
    let c = t.chars().next()?;
    if c != '`' && c != '~' {
        return None;
    }
    let n = t.chars().take_while(|&x| x == c).count();
    (n >= 3).then_some((c, n))
}

/// The file's lines outside fenced code blocks, and the contents of the fenced blocks in order.
fn split_fences(text: &str) -> (Vec<String>, Vec<String>) {
    let (mut prose, mut blocks) = (Vec::new(), Vec::new());
    let mut open: Option<(char, usize)> = None;
    let mut block = String::new();
    for line in text.lines() {
        match (open, fence(line)) {
            (None, Some(f)) => {
                open = Some(f);
                block.clear();
            }
            (Some((c, n)), Some((c2, n2))) if c == c2 && n2 >= n && line.trim().chars().all(|x| x == c) => {
                open = None;
                blocks.push(std::mem::take(&mut block));
            }
            (Some(_), _) => {
                block.push_str(line);
                block.push('\n');
            }
            (None, None) => prose.push(line.to_string()),
        }
    }
    (prose, blocks)
}

/// A line with its code spans (`…`, ``…``) removed.
fn strip_code_spans(line: &str) -> String {
    let mut out = String::new();
    let mut rest = line;
    while let Some(i) = rest.find('`') {
        out.push_str(&rest[..i]);
        let ticks = rest[i..].chars().take_while(|&c| c == '`').count();
        let after = &rest[i + ticks..];
        let close = "`".repeat(ticks);
        match after.find(&close) {
            Some(j) => rest = &after[j + ticks..],
            None => {
                out.push_str(&rest[i..i + ticks]);
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// Every link target in a Markdown text: inline `](target)` and reference definitions `[label]: target`.
fn link_targets(text: &str) -> Vec<String> {
    let (prose, _) = split_fences(text);
    let mut out = Vec::new();
    for line in &prose {
        let line = strip_code_spans(line);
        let mut rest = line.as_str();
        while let Some(i) = rest.find("](") {
            let after = &rest[i + 2..];
            let mut depth = 0usize;
            let mut end = after.len();
            for (k, c) in after.char_indices() {
                match c {
                    '(' => depth += 1,
                    ')' if depth == 0 => {
                        end = k;
                        break;
                    }
                    ')' => depth -= 1,
                    _ => {}
                }
            }
            let inner = after[..end].trim();
            let target = inner.strip_prefix('<').and_then(|s| s.split('>').next()).unwrap_or_else(|| inner.split_whitespace().next().unwrap_or(""));
            if !target.is_empty() {
                out.push(target.to_string());
            }
            rest = &after[end.min(after.len())..];
        }
        let t = line.trim_start();
        if let (Some(rest), Some(k)) = (t.strip_prefix('['), t.find(']')) {
            if !rest.starts_with('^') && t[k + 1..].starts_with(':') {
                if let Some(target) = t[k + 2..].split_whitespace().next() {
                    out.push(target.to_string());
                }
            }
        }
    }
    out
}

/// GitHub's anchor of a heading's text.
fn slug(heading: &str) -> String {
    // Inline links render as their text: `[text](url)` → `text`.
    let mut text = String::new();
    let mut rest = heading;
    while let Some(i) = rest.find("](") {
        let Some(close) = rest[i..].find(')') else { break };
        text.push_str(&rest[..i]);
        rest = &rest[i + close + 1..];
    }
    text.push_str(rest);
    text.trim().to_lowercase().chars().filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_').map(|c| if c == ' ' { '-' } else { c }).collect()
}

/// The anchors a Markdown file offers: its headings' slugs (repeats numbered) and explicit `id`/`name` anchors.
fn anchors(text: &str) -> HashSet<String> {
    let (prose, _) = split_fences(text);
    let mut seen: std::collections::HashMap<String, usize> = Default::default();
    let mut out = HashSet::new();
    for line in &prose {
        let t = line.trim_start();
        let hashes = t.chars().take_while(|&c| c == '#').count();
        if (1..=6).contains(&hashes) && t[hashes..].starts_with(' ') {
            let h = t[hashes..].trim().trim_end_matches('#').trim();
            let s = slug(h);
            let n = seen.entry(s.clone()).or_insert(0);
            out.insert(if *n == 0 { s.clone() } else { format!("{s}-{n}") });
            *n += 1;
        }
        for key in ["id=\"", "name=\""] {
            let mut rest = line.as_str();
            while let Some(i) = rest.find(key) {
                let after = &rest[i + key.len()..];
                if let Some(j) = after.find('"') {
                    out.insert(after[..j].to_string());
                }
                rest = after;
            }
        }
    }
    out
}

fn has_scheme(target: &str) -> bool {
    match target.find(':') {
        Some(i) => target[..i].chars().all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c)) && i > 0,
        None => false,
    }
}

/// A path joined lexically (`a/b/../c` → `a/c`), as a browser resolves a relative link.
fn normalise(p: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

/// What is wrong with the relative links of the Markdown file `file`: one line per broken link.
fn broken_links(file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("reading {}: {e}", file.display()));
    let dir = file.parent().unwrap();
    let mut out = Vec::new();
    for target in link_targets(&text) {
        if has_scheme(&target) {
            continue;
        }
        let (path, anchor) = match target.split_once('#') {
            Some((p, a)) => (p, Some(a)),
            None => (target.as_str(), None),
        };
        let path = path.replace("%20", " ");
        let resolved = if path.is_empty() { file.to_path_buf() } else { normalise(&dir.join(&path)) };
        if !resolved.exists() {
            out.push(format!("{}: link `{target}`: {} does not exist", file.display(), resolved.display()));
            continue;
        }
        if let Some(anchor) = anchor {
            if resolved.extension().is_some_and(|e| e == "md") {
                let t = std::fs::read_to_string(&resolved).unwrap();
                if !anchors(&t).contains(&anchor.to_lowercase()) {
                    out.push(format!("{}: link `{target}`: {} has no heading with anchor #{anchor}", file.display(), resolved.display()));
                }
            }
        }
    }
    out
}

fn markdown_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            markdown_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "md") {
            out.push(p);
        }
    }
}

#[test]
fn every_relative_link_in_readme_and_docs_resolves() {
    let root = normalise(&std::fs::canonicalize(root()).unwrap());
    let mut files = vec![root.join("README.md")];
    markdown_files(&root.join("docs"), &mut files);
    assert!(files.len() > 5, "expected README.md and the docs/ pages, found {files:?}");
    let broken: Vec<String> = files.iter().flat_map(|f| broken_links(f)).collect();
    assert!(broken.is_empty(), "{} broken link(s):\n{}", broken.len(), broken.join("\n"));
}

#[test]
fn readme_is_a_front_page_with_the_two_commands_first() {
    let text = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert!(text.len() <= README_MAX_BYTES, "README.md is {} bytes; the front page stays ≤ {README_MAX_BYTES} (move detail to docs/)", text.len());
    let (_, blocks) = split_fences(&text);
    assert!(blocks.len() >= 2, "README.md has {} fenced code blocks; the first two are the demo and scripts/test", blocks.len());
    assert!(blocks[0].contains(DEMO_COMMAND), "README.md's first fenced code block must be the demo command `{DEMO_COMMAND}`, found:\n{}", blocks[0]);
    assert!(blocks[1].contains(TEST_COMMAND), "README.md's second fenced code block must be `{TEST_COMMAND}`, found:\n{}", blocks[1]);
}

/// The checker itself: a missing file, a missing heading, a heading only inside a code block and a broken reference
/// definition are reported; code, external links, folders and existing headings (GitHub's slugs) are not.
#[test]
fn the_checker_finds_broken_links() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    std::fs::create_dir_all(d.join("docs/sub")).unwrap();
    std::fs::write(
        d.join("docs/target.md"),
        "# Target\n\n## `render`: the main job (v2)\n\n## Repeat\n\n## Repeat\n\n## 6. Official weights\n\n```\n# not a heading\n```\n",
    )
    .unwrap();
    std::fs::write(
        d.join("docs/page.md"),
        "# Page\n\n[ok](target.md) [ok](target.md#render-the-main-job-v2) [ok](target.md#repeat-1) \
         [ok](target.md#6-official-weights) [ok](sub/) [ok](#page) [ext](https://example.com/x.md#y) \
         `[code](missing.md)`\n\n```\n[fenced](missing.md)\n```\n\n\
         [bad](missing.md)\n[bad](target.md#no-such-heading)\n[bad](target.md#not-a-heading)\n\
         [label]: gone.md\n",
    )
    .unwrap();
    let broken = broken_links(&d.join("docs/page.md"));
    let named = |s: &str| broken.iter().any(|b| b.contains(s));
    assert!(named("`missing.md`") && named("#no-such-heading") && named("#not-a-heading") && named("`gone.md`"), "{broken:#?}");
    assert_eq!(broken.len(), 4, "only the four bad links: {broken:#?}");
}
