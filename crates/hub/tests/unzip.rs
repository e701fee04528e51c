//! Data zips: unpacked once into a folder keyed by the zip's SHA-256; zip-slip, links and oversize refused.

use mvsplat360_hub::{unpack_zip, unpack_zip_with, Error, UnpackLimits};
use std::io::Write;
use std::path::Path;
use zip::write::SimpleFileOptions;

enum Entry<'a> {
    File(&'a str, &'a [u8]),
    Dir(&'a str),
    Link(&'a str, &'a str),
}

fn make_zip(path: &Path, entries: &[Entry]) {
    let mut w = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let opt = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    for e in entries {
        match e {
            Entry::File(n, b) => {
                w.start_file(*n, opt).unwrap();
                w.write_all(b).unwrap();
            }
            Entry::Dir(n) => w.add_directory(*n, opt).unwrap(),
            Entry::Link(n, t) => w.add_symlink(*n, *t, opt).unwrap(),
        }
    }
    w.finish().unwrap();
}

fn sha256(path: &Path) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(std::fs::read(path).unwrap()).iter().map(|b| format!("{b:02x}")).collect()
}

fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).map(|r| r.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect()).unwrap_or_default();
    v.sort();
    v
}

#[test]
fn unpacked_once_keyed_by_the_zip_hash() {
    let tmp = tempfile::tempdir().unwrap();
    let z = tmp.path().join("data.zip");
    make_zip(&z, &[Entry::Dir("dl3dv_tiny/"), Entry::File("dl3dv_tiny/test/000000.torch", &[7u8; 10_000]), Entry::File("dl3dv_tiny/test/index.json", b"{}")]);
    let root = tmp.path().join("cache/data");
    let dir = unpack_zip(&z, &root).unwrap();
    assert_eq!(dir, root.join(sha256(&z)));
    assert_eq!(std::fs::read(dir.join("dl3dv_tiny/test/000000.torch")).unwrap(), vec![7u8; 10_000]);
    assert_eq!(std::fs::read(dir.join("dl3dv_tiny/test/index.json")).unwrap(), b"{}");
    assert_eq!(listing(&root), vec![sha256(&z)], "a temporary folder was left");
    // Once: a second call finds the folder (a file changed inside stays changed).
    std::fs::write(dir.join("dl3dv_tiny/test/index.json"), b"mine").unwrap();
    assert_eq!(unpack_zip(&z, &root).unwrap(), dir);
    assert_eq!(std::fs::read(dir.join("dl3dv_tiny/test/index.json")).unwrap(), b"mine");
}

fn refused(entries: &[Entry], limits: UnpackLimits, want: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let z = tmp.path().join("bad.zip");
    make_zip(&z, entries);
    let root = tmp.path().join("cache");
    let e = unpack_zip_with(&z, &root, limits).unwrap_err();
    assert!(matches!(e, Error::Zip(_)), "{e}");
    assert!(e.to_string().contains(want), "{want:?} not in: {e}");
    assert!(listing(&root).is_empty(), "left behind: {:?}", listing(&root));
    assert_eq!(listing(tmp.path()), vec!["bad.zip".to_string(), "cache".to_string()], "written outside");
}

#[test]
fn entries_leaving_the_folder_are_refused() {
    refused(&[Entry::File("ok.txt", b"x"), Entry::File("../evil.txt", b"x")], UnpackLimits::default(), "outside the folder");
    refused(&[Entry::File("a/../../evil.txt", b"x")], UnpackLimits::default(), "outside the folder");
    refused(&[Entry::File("/tmp/evil-absolute.txt", b"x")], UnpackLimits::default(), "outside the folder");
}

#[test]
fn links_are_refused() {
    refused(&[Entry::File("a.txt", b"x"), Entry::Link("b", "/etc/passwd")], UnpackLimits::default(), "is a link");
}

#[test]
fn too_many_entries_or_bytes_are_refused() {
    let many: Vec<String> = (0..6).map(|i| format!("f{i}")).collect();
    let entries: Vec<Entry> = many.iter().map(|n| Entry::File(n, b"x")).collect();
    refused(&entries, UnpackLimits { max_entries: 5, max_bytes: 1 << 20 }, "6 entries, more than the 5 allowed");
    // 4 MB of zeros compress to a few KB: the bound counts what is written.
    let zeros = vec![0u8; 4 << 20];
    refused(&[Entry::File("a.bin", &zeros)], UnpackLimits { max_entries: 10, max_bytes: 1 << 20 }, "more than the 1048576 bytes allowed");
    refused(
        &[Entry::File("a.bin", &zeros[..600_000]), Entry::File("b.bin", &zeros[..600_000])],
        UnpackLimits { max_entries: 10, max_bytes: 1 << 20 },
        "bytes allowed",
    );
}
