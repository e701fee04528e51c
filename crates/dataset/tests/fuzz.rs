//! Seeded mutations of the readers' inputs (COLMAP binary and text models, `transforms.json`, `.torch` chunks,
//! PNG and JPEG photos): every case must end in `Ok` or an error, never a panic, and quickly (a watchdog ends
//! the run on a case that hangs). The seed files are the project's own
//! (assets/woodbox, the test chunk); the mutations are byte flips, truncations, inserted bytes and fields
//! overwritten with extreme values (binary), and replaced, dropped or doubled tokens (text). A fixed seed here;
//! `MVSPLAT360_FUZZ_SEED` and `MVSPLAT360_FUZZ_CASES` run other and longer hunts.

use std::path::Path;
use std::time::{Duration, Instant};

use mvsplat360_testkit::mutate::{mutate_binary, mutate_zip_entry, Rng, EXTREMES};

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

fn seed() -> u64 {
    std::env::var("MVSPLAT360_FUZZ_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(20261202)
}

fn cases(default: usize) -> usize {
    std::env::var("MVSPLAT360_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}

const TOKENS: [&str; 12] = ["-1", "0", "1e308", "-1e308", "NaN", "inf", "18446744073709551616", "4294967296", "x", "", "{", "\"a\""];

fn mutate_text(rng: &mut Rng, text: &str) -> String {
    let mut toks: Vec<String> = text.split_inclusive(|c: char| c.is_whitespace() || c == ',' || c == ':').map(str::to_string).collect();
    for _ in 0..1 + rng.below(3) {
        if toks.is_empty() {
            break;
        }
        let i = rng.below(toks.len());
        match rng.below(4) {
            0 => toks[i] = format!("{} ", TOKENS[rng.below(TOKENS.len())]),
            1 => {
                toks.remove(i);
            }
            2 => {
                let t = toks[i].clone();
                toks.insert(i, t);
            }
            _ => toks.truncate(i),
        }
    }
    toks.concat()
}

/// A case that runs this long is a hang: the watchdog keeps its input and ends the test process.
const HANG: Duration = Duration::from_secs(20);

/// Told each case as it starts; a case that does not end within [`HANG`] aborts the run, naming it.
fn watchdog(name: &str, target: &Path) -> std::sync::mpsc::Sender<usize> {
    let (tx, rx) = std::sync::mpsc::channel::<usize>();
    let (name, target) = (name.to_string(), target.to_path_buf());
    std::thread::spawn(move || {
        let mut case = None;
        loop {
            match rx.recv_timeout(HANG) {
                Ok(c) => case = Some(c),
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return,
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                    if let Some(c) = case {
                        let keep = std::env::temp_dir().join(format!("fuzz-hang-{name}-{c}"));
                        let _ = std::fs::copy(&target, &keep);
                        eprintln!("{name}: case {c} (seed {}) has run over {HANG:?}: a hang; its input is kept in {}", seed(), keep.display());
                        std::process::abort();
                    }
                }
            }
        }
    });
    tx
}

/// Runs `read` on each mutated file; panics are collected and reported with the case that caused them.
fn fuzz(name: &str, seed_file: &Path, n: usize, mutate: impl Fn(&mut Rng, &[u8]) -> Vec<u8>, read: impl Fn(&Path) -> bool) {
    let dir = tempfile::tempdir().unwrap();
    let original = std::fs::read(seed_file).unwrap();
    let mut rng = Rng(seed() ^ name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3)));
    let target = dir.path().join(seed_file.file_name().unwrap());
    let (mut ok, mut errors, mut panics) = (0, 0, Vec::new());
    let t0 = Instant::now();
    let dog = watchdog(name, &target);
    for case in 0..n {
        let bytes = mutate(&mut rng, &original);
        std::fs::write(&target, &bytes).unwrap();
        dog.send(case).unwrap();
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read(&target))) {
            Ok(true) => ok += 1,
            Ok(false) => errors += 1,
            Err(_) => {
                let keep = dir.path().join(format!("panic-{case}"));
                std::fs::copy(&target, &keep).unwrap();
                panics.push(case);
            }
        }
    }
    eprintln!("{name}: {n} cases ({ok} read, {errors} refused) in {:.1} s, seed {}", t0.elapsed().as_secs_f64(), seed());
    if !panics.is_empty() {
        let kept = dir.keep();
        panic!("{name}: {} case(s) panicked: {:?}; inputs kept in {}", panics.len(), &panics[..panics.len().min(10)], kept.display());
    }
}

/// Offsets of the 8-byte count fields of a COLMAP `images.bin` (the image count, each image's point count) and of
/// a `cameras.bin` (the camera count, each width and height), where a crafted file puts its absurd values.
fn count_fields(data: &[u8], images: bool) -> Vec<usize> {
    let u64_at = |i: usize| data.get(i..i + 8).map(|b| u64::from_le_bytes(b.try_into().unwrap()));
    let mut out = vec![0];
    let mut pos = 8;
    for _ in 0..u64_at(0).unwrap_or(0) {
        if images {
            pos += 4 + 32 + 24 + 4;
            let Some(end) = data.get(pos..).and_then(|r| r.iter().position(|&b| b == 0)) else { break };
            pos += end + 1;
            out.push(pos);
            pos += 8 + 24 * u64_at(pos).unwrap_or(0) as usize;
        } else {
            let params = match data.get(pos + 4..pos + 8).map(|b| i32::from_le_bytes(b.try_into().unwrap())) {
                Some(0) => 3,
                Some(1) | Some(2) => 4,
                Some(3) => 5,
                Some(4) => 8,
                _ => break,
            };
            out.extend([pos + 8, pos + 16]);
            pos += 24 + 8 * params;
        }
    }
    out
}

/// [`mutate_binary`], or (a third of the cases) one count field set to an extreme value.
fn mutate_colmap(images: bool) -> impl Fn(&mut Rng, &[u8]) -> Vec<u8> {
    move |rng, data| {
        let fields = count_fields(data, images);
        if rng.below(3) > 0 {
            return mutate_binary(rng, data);
        }
        let mut d = data.to_vec();
        let at = fields[rng.below(fields.len())];
        if at + 8 <= d.len() {
            d[at..at + 8].copy_from_slice(&EXTREMES[rng.below(EXTREMES.len())].to_le_bytes());
        }
        d
    }
}

#[test]
fn colmap_binary_models() {
    let sparse = root().join("assets/woodbox/sparse/0");
    fuzz("cameras.bin", &sparse.join("cameras.bin"), cases(1500), mutate_colmap(false), |p| mvsplat360_dataset::colmap::read_cameras_bin(p).is_ok());
    fuzz("images.bin", &sparse.join("images.bin"), cases(1500), mutate_colmap(true), |p| mvsplat360_dataset::colmap::read_images_bin(p).is_ok());
}

#[test]
fn colmap_text_models() {
    let sparse = root().join("assets/woodbox/sparse_txt/0");
    let text = |r: &mut Rng, b: &[u8]| mutate_text(r, &String::from_utf8_lossy(b)).into_bytes();
    fuzz("cameras.txt", &sparse.join("cameras.txt"), cases(1500), text, |p| mvsplat360_dataset::colmap::read_cameras_txt(p).is_ok());
    fuzz("images.txt", &sparse.join("images.txt"), cases(1500), text, |p| mvsplat360_dataset::colmap::read_images_txt(p).is_ok());
}

#[test]
fn transforms_json_scenes() {
    // The scene folder: the mutated transforms.json beside a link to the bundled images.
    let dir = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink(root().join("assets/woodbox/images"), dir.path().join("images")).unwrap();
    let seed_file = root().join("assets/woodbox/transforms.json");
    let scene = dir.path().join("transforms.json");
    let text = |r: &mut Rng, b: &[u8]| mutate_text(r, &String::from_utf8_lossy(b)).into_bytes();
    let original = std::fs::read(&seed_file).unwrap();
    let mut rng = Rng(seed());
    let mut panics = vec![];
    let n = cases(1500);
    for case in 0..n {
        std::fs::write(&scene, text(&mut rng, &original)).unwrap();
        if std::panic::catch_unwind(|| mvsplat360_dataset::read_scene(dir.path()).map(|s| s.validate())).is_err() {
            panics.push(case);
        }
    }
    assert!(panics.is_empty(), "transforms.json: cases {panics:?} panicked (seed {})", seed());
}

fn mutate_chunk(rng: &mut Rng, data: &[u8]) -> Vec<u8> {
    mutate_zip_entry(rng, data, "data.pkl")
}

#[test]
fn torch_chunks() {
    let chunk = root().join("crates/dataset/tests/data/chunk/000000.torch");
    fuzz("000000.torch", &chunk, cases(400), mutate_chunk, |p| {
        mvsplat360_dataset::torch_chunk::read_chunk(p).is_ok_and(|scenes| scenes.into_iter().all(|s| s.into_scene(p).is_ok()))
    });
}

/// The inputs the hunts found panicking (tests/data/fuzz/README.md): each is now one clear refusal.
#[test]
fn found_cases_are_refused() {
    for (file, says) in [("long1-over-8-bytes.torch", "malformed pickle"), ("short-storage-tuple.torch", "malformed tensor record")] {
        let p = root().join("crates/dataset/tests/data/fuzz").join(file);
        let e = mvsplat360_dataset::torch_chunk::read_chunk(&p).and_then(|v| v.into_iter().map(|s| s.into_scene(&p)).collect::<Result<Vec<_>, _>>());
        let e = e.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains(says) && e.contains(file), "{file}: {e}");
    }
}

/// CRC-32 (IEEE) of a PNG chunk's type and data.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A PNG with its IHDR width and height set to `w`×`h` (the chunk's CRC made right, so the decoder reads them).
fn png_claiming(png: &[u8], w: u32, h: u32) -> Vec<u8> {
    let mut d = png.to_vec();
    d[16..20].copy_from_slice(&w.to_be_bytes());
    d[20..24].copy_from_slice(&h.to_be_bytes());
    let crc = crc32(&d[12..29]);
    d[29..33].copy_from_slice(&crc.to_be_bytes());
    d
}

/// Offset of a JPEG's frame header (SOF0–SOF2) height field; width follows.
fn jpeg_size_field(d: &[u8]) -> Option<usize> {
    (2..d.len().saturating_sub(8)).find(|&i| d[i] == 0xFF && matches!(d[i + 1], 0xC0..=0xC2)).map(|i| i + 5)
}

/// A PNG with one chunk's data mutated ([`mutate_binary`]; the image data half the time) and its length and CRC
/// made right, so that the mutation reaches the inflater and the row filters rather than the checksum.
fn mutate_png_chunk(rng: &mut Rng, d: &[u8]) -> Vec<u8> {
    let mut chunks = vec![];
    let mut i = 8;
    while i + 12 <= d.len() {
        let n = u32::from_be_bytes(d[i..i + 4].try_into().unwrap()) as usize;
        if i + 12 + n > d.len() {
            break;
        }
        chunks.push((i, n));
        i += 12 + n;
    }
    let idat: Vec<usize> = (0..chunks.len()).filter(|&k| &d[chunks[k].0 + 4..chunks[k].0 + 8] == b"IDAT").collect();
    let k = if !idat.is_empty() && rng.below(2) == 0 { idat[rng.below(idat.len())] } else { rng.below(chunks.len()) };
    let (at, n) = chunks[k];
    let data = mutate_binary(rng, &d[at + 8..at + 8 + n]);
    let mut body = d[at + 4..at + 8].to_vec();
    body.extend_from_slice(&data);
    let mut out = d[..at].to_vec();
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    out.extend_from_slice(&body);
    out.extend_from_slice(&crc32(&body).to_be_bytes());
    out.extend_from_slice(&d[at + 12 + n..]);
    out
}

/// [`mutate_binary`]; a PNG chunk's data ([`mutate_png_chunk`]); or the image's claimed width and height set to
/// extreme values.
fn mutate_image(rng: &mut Rng, d: &[u8]) -> Vec<u8> {
    let png = d.starts_with(b"\x89PNG");
    match rng.below(3) {
        0 => return mutate_binary(rng, d),
        1 if png => return mutate_png_chunk(rng, d),
        1 => return mutate_binary(rng, d),
        _ => {}
    }
    const SIDES: [u32; 8] = [0, 1, 2, 16385, 65535, 40000, 1 << 24, u32::MAX];
    let (w, h) = (SIDES[rng.below(SIDES.len())], SIDES[rng.below(SIDES.len())]);
    if png {
        return png_claiming(d, w, h);
    }
    let mut d = d.to_vec();
    if let Some(i) = jpeg_size_field(&d) {
        d[i..i + 2].copy_from_slice(&(h.min(65535) as u16).to_be_bytes());
        d[i + 2..i + 4].copy_from_slice(&(w.min(65535) as u16).to_be_bytes());
    }
    d
}

/// The bundled scene's first photo as a JPEG (as shipped) and as a PNG (written here).
fn image_seeds(dir: &Path) -> [std::path::PathBuf; 2] {
    let jpg = root().join("assets/woodbox/images/000.jpg");
    let png = dir.join("000.png");
    image::open(&jpg).unwrap().save(&png).unwrap();
    [jpg, png]
}

fn read_image(p: &Path) -> bool {
    let src = mvsplat360_dataset::image::ImageSource::File(p.to_path_buf());
    let _ = src.exif_orientation();
    let dims = src.dimensions();
    let img = src.decode();
    if let (Ok(d), Ok(i)) = (&dims, &img) {
        assert_eq!(*d, (i.width, i.height), "the header's size is the decoded size");
        assert!(i.data.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
    }
    img.is_ok()
}

#[test]
fn png_and_jpeg_photos() {
    let dir = tempfile::tempdir().unwrap();
    for seed_file in image_seeds(dir.path()) {
        let name = seed_file.file_name().unwrap().to_string_lossy().into_owned();
        fuzz(&name, &seed_file, cases(1500), mutate_image, read_image);
    }
}

/// A few bytes claiming a huge image are refused before the decoder allocates it; a side over the limit is
/// refused naming the limit; the seeds themselves read.
#[test]
fn claimed_image_sizes_are_checked_against_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let [jpg, png] = image_seeds(dir.path());
    let bytes = std::fs::read(&png).unwrap();
    let decode = |name: &str, b: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, b).unwrap();
        mvsplat360_dataset::image::ImageSource::File(p).decode().err().map(|e| e.to_string()).unwrap_or_default()
    };
    assert!(read_image(&jpg) && read_image(&png));
    // 8000×8000 RGB8 = 192 MB from the first 2000 bytes: more than any PNG of that length can hold (~66 MB).
    let e = decode("claims.png", &png_claiming(&bytes[..2000], 8000, 8000));
    assert!(e.contains("claims.png") && e.contains("more than a file of 2000 bytes"), "{e}");
    // The same size from the whole file (~100 KB) is possible for deflate: decoded, it is refused as truncated.
    let e = decode("truncated.png", &png_claiming(&bytes, 8000, 8000));
    assert!(e.contains("truncated.png") && !e.contains("more than a file of"), "{e}");
    let e = decode("wide.png", &png_claiming(&bytes, 20000, 8));
    assert!(e.contains("wide.png") && e.contains("16384 pixels a side"), "{e}");
    let mut j = std::fs::read(&jpg).unwrap();
    let i = jpeg_size_field(&j).unwrap();
    j[i..i + 4].copy_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]);
    let e = decode("claims.jpg", &j);
    assert!(e.contains("claims.jpg") && e.contains("16384 pixels a side"), "{e}");
}
