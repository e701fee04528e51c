//! The shipped model's card (`assets/models/default/MODEL.md`): short enough to read in two minutes, laid out
//! as a Hugging Face card, and every link it gives leads to a file of the repository.

use std::path::{Path, PathBuf};

/// DESIGN.md's bound for the card.
const MAX_BYTES: usize = 15 * 1024;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn card() -> (PathBuf, String) {
    let path = repo().join("assets/models/default/MODEL.md");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (path, text)
}

#[test]
fn card_is_short_and_has_the_card_layout() {
    let (path, text) = card();
    assert!(text.len() <= MAX_BYTES, "{} is {} bytes, more than {MAX_BYTES}: move details to docs/research/", path.display(), text.len());
    // YAML front matter first, with a licence.
    let front = text.strip_prefix("---\n").and_then(|t| t.split_once("\n---\n")).map(|(f, _)| f).expect("YAML front matter between --- lines");
    assert!(front.lines().any(|l| l.starts_with("license:")), "front matter without `license:`");
    let headings: Vec<&str> = text.lines().filter(|l| l.starts_with("## ")).collect();
    for want in ["## Intended use", "## Out-of-scope use", "## Training", "## Evaluation", "## Limitations"] {
        assert!(headings.iter().any(|h| h.starts_with(want)), "no `{want}` section (sections: {headings:?})");
    }
}

#[test]
fn card_links_resolve() {
    let (path, text) = card();
    let dir = path.parent().unwrap();
    let mut checked = 0;
    for part in text.split("](").skip(1) {
        let target = part.split(')').next().unwrap();
        if target.starts_with("http") || target.starts_with('#') {
            continue;
        }
        let file = target.split('#').next().unwrap();
        assert!(dir.join(file).exists(), "{}: link `{target}` leads nowhere", path.display());
        checked += 1;
    }
    assert!(checked > 0, "the card links to no study in docs/research/");
}
