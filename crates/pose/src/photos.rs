//! Photos from a folder: EXIF orientation baked into the pixels (COLMAP reads the stored grid and ignores the
//! tag, so an upright phone photo would be posed lying on its side), ordered by EXIF capture time then name,
//! scaled to the long side limit, and written with an order prefix (COLMAP's sequential matcher follows names).

use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageDecoder, ImageReader};
use serde::Serialize;

use crate::error::PoseError;
use crate::Progress;

/// Extensions read as photos (what the image decoder here and COLMAP both read).
pub const EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

fn is_photo(p: &Path) -> bool {
    p.extension().and_then(|e| e.to_str()).is_some_and(|e| EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// The photos of `dir` (not its subfolders), and the other files there (named in a note, not read).
pub fn list(dir: &Path) -> Result<(Vec<PathBuf>, Vec<String>), PoseError> {
    let mut photos = vec![];
    let mut others = vec![];
    for e in std::fs::read_dir(dir).map_err(|e| PoseError::io(dir, e))? {
        let e = e.map_err(|e| PoseError::io(dir, e))?;
        let p = e.path();
        if !p.is_file() {
            continue;
        }
        if is_photo(&p) {
            photos.push(p);
        } else if !e.file_name().to_string_lossy().starts_with('.') {
            others.push(e.file_name().to_string_lossy().into_owned());
        }
    }
    photos.sort();
    others.sort();
    Ok((photos, others))
}

#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Photo {
    pub source: String,
    pub file: String,
    pub orientation: u8,
    pub taken: Option<String>,
    pub size: (u32, u32),
    /// EXIF `Make`, `Model`, `FocalLength` (mm): with the size, what tells one camera from another.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub make: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focal_mm: Option<f64>,
}

/// What `pose` reads of a photo's EXIF.
#[derive(Debug, Clone, Default, PartialEq)]
struct ExifInfo {
    /// `DateTimeOriginal` (else `DateTime`), as `YYYY:MM:DD HH:MM:SS` (sorts as text).
    taken: Option<String>,
    make: Option<String>,
    model: Option<String>,
    focal_mm: Option<f64>,
}

fn exif_text(ex: &exif::Exif, tag: exif::Tag) -> Option<String> {
    let f = ex.get_field(tag, exif::In::PRIMARY)?;
    let exif::Value::Ascii(v) = &f.value else { return None };
    // Writers pad with NULs and spaces.
    let s = String::from_utf8_lossy(v.first()?).trim_matches(|c: char| c == '\0' || c.is_whitespace()).to_string();
    (!s.is_empty()).then_some(s)
}

/// The EXIF of raw EXIF bytes (unreadable: nothing known).
fn exif_info(raw: Vec<u8>) -> ExifInfo {
    let Ok(ex) = exif::Reader::new().read_raw(raw) else { return ExifInfo::default() };
    let focal_mm = ex.get_field(exif::Tag::FocalLength, exif::In::PRIMARY).and_then(|f| match &f.value {
        exif::Value::Rational(v) => v.first().map(|r| r.to_f64()).filter(|f| f.is_finite() && *f > 0.0),
        _ => None,
    });
    ExifInfo {
        taken: exif_text(&ex, exif::Tag::DateTimeOriginal).or_else(|| exif_text(&ex, exif::Tag::DateTime)),
        make: exif_text(&ex, exif::Tag::Make),
        model: exif_text(&ex, exif::Tag::Model),
        focal_mm,
    }
}

struct Decoded {
    img: DynamicImage,
    orientation: u8,
    exif: ExifInfo,
}

fn decode(p: &Path) -> Result<Decoded, PoseError> {
    let bad = |msg: String| PoseError::input(p, format!("cannot decode this photo ({msg}); remove it or replace it with a readable JPEG/PNG"));
    let len = std::fs::metadata(p).map_err(|e| PoseError::io(p, e))?.len();
    let reader = ImageReader::open(p).map_err(|e| PoseError::io(p, e))?.with_guessed_format().map_err(|e| bad(e.to_string()))?;
    let mut dec = mvsplat360_dataset::image::limited_decoder(reader, len).map_err(bad)?;
    let orient = dec.orientation().unwrap_or(image::metadata::Orientation::NoTransforms);
    let exif = dec.exif_metadata().ok().flatten().map(exif_info).unwrap_or_default();
    let mut img = DynamicImage::from_decoder(dec).map_err(|e| bad(e.to_string()))?;
    img.apply_orientation(orient);
    Ok(Decoded { img, orientation: orient.to_exif(), exif })
}

/// Reads, orders and writes the photos into `dir`; `max_size` limits the long side.
pub fn prepare(photos: &[PathBuf], max_size: u32, dir: &Path, progress: &dyn Progress) -> Result<Vec<Photo>, PoseError> {
    // Order first (times come from the headers), then decode one at a time.
    let mut keyed = vec![];
    for p in photos {
        let taken = ImageReader::open(p)
            .ok()
            .and_then(|r| r.with_guessed_format().ok())
            .and_then(|r| r.into_decoder().ok())
            .and_then(|mut d| d.exif_metadata().ok().flatten())
            .and_then(|raw| exif_info(raw).taken);
        keyed.push((taken, p.clone()));
    }
    // Photos with a capture time first, by time; then the others; names break ties.
    keyed.sort_by(|a, b| (a.0.is_none(), &a.0, &a.1).cmp(&(b.0.is_none(), &b.0, &b.1)));
    let width = keyed.len().to_string().len().max(4);
    progress.begin("photos", keyed.len() as u64);
    let mut out = vec![];
    for (k, (_, p)) in keyed.iter().enumerate() {
        let d = decode(p)?;
        let (w, h) = (d.img.width(), d.img.height());
        let (tw, th) = if w.max(h) > max_size {
            let s = max_size as f64 / w.max(h) as f64;
            (((w as f64 * s).round() as u32).max(1), ((h as f64 * s).round() as u32).max(1))
        } else {
            (w, h)
        };
        let stem = p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let source = p.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let unchanged = (tw, th) == (w, h) && d.orientation <= 1;
        // Unchanged pixels keep the original bytes; turned or scaled ones are written losslessly (a second JPEG
        // compression costs COLMAP accuracy, see video.rs).
        let ext = if unchanged { p.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default() } else { "png".into() };
        let file = format!("{k:0width$}_{stem}.{ext}");
        let target = dir.join(&file);
        if unchanged {
            std::fs::copy(p, &target).map_err(|e| PoseError::io(&target, e))?;
        } else {
            let img = if (tw, th) == (w, h) { d.img } else { d.img.resize_exact(tw, th, image::imageops::FilterType::Lanczos3) };
            let rgb = img.to_rgb8();
            let f = std::fs::File::create(&target).map_err(|e| PoseError::io(&target, e))?;
            rgb.write_to(&mut std::io::BufWriter::new(f), image::ImageFormat::Png).map_err(|e| PoseError::io(&target, std::io::Error::other(e)))?;
        }
        let ExifInfo { taken, make, model, focal_mm } = d.exif;
        out.push(Photo { source, file, orientation: d.orientation, taken, size: (tw, th), make, model, focal_mm });
        progress.set(k as u64 + 1);
    }
    progress.end();
    Ok(out)
}

/// One COLMAP camera: the photos of one size from one device (EXIF make, model, focal length).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraGroup {
    /// The subfolder of `images/` its photos go to (when there are several groups).
    pub folder: String,
    pub size: (u32, u32),
    pub make: Option<String>,
    pub model: Option<String>,
    pub focal_mm: Option<f64>,
    pub photos: usize,
}

/// Groups photos into COLMAP cameras by size and EXIF make, model and focal length (two phones with one
/// sensor size are two cameras; a zoom's focal lengths are too), and each photo's group. A folder is named
/// by the size, `WxH`, with `-N` when that size holds several devices.
pub fn camera_groups(photos: &[Photo]) -> (Vec<CameraGroup>, Vec<usize>) {
    type Key = ((u32, u32), Option<String>, Option<String>, Option<String>);
    let key = |p: &Photo| -> Key { (p.size, p.make.clone(), p.model.clone(), p.focal_mm.map(|f| format!("{f}"))) };
    let keys: std::collections::BTreeSet<Key> = photos.iter().map(key).collect();
    let keys: Vec<Key> = keys.into_iter().collect();
    let groups = keys
        .iter()
        .map(|k| {
            let same_size: Vec<&Key> = keys.iter().filter(|o| o.0 == k.0).collect();
            let folder = match same_size.iter().position(|o| *o == k) {
                Some(i) if same_size.len() > 1 => format!("{}x{}-{}", k.0 .0, k.0 .1, i + 1),
                _ => format!("{}x{}", k.0 .0, k.0 .1),
            };
            let first = photos.iter().find(|p| key(p) == *k);
            CameraGroup {
                folder,
                size: k.0,
                make: k.1.clone(),
                model: k.2.clone(),
                focal_mm: first.and_then(|p| p.focal_mm),
                photos: photos.iter().filter(|p| key(p) == *k).count(),
            }
        })
        .collect();
    let of = photos.iter().map(|p| keys.iter().position(|k| *k == key(p)).unwrap_or(0)).collect();
    (groups, of)
}

/// ` (other files: a, b)` for a refusal that names what else the folder holds; empty when nothing.
pub fn others_suffix(others: &[String]) -> String {
    if others.is_empty() {
        String::new()
    } else {
        format!(" (other files: {})", others.join(", "))
    }
}

/// Says which files of `dir` are not photos and are left out.
pub fn note_ignored(dir: &Path, others: &[String], progress: &dyn crate::Progress) {
    if !others.is_empty() {
        progress.note(&format!("note: {}: ignoring {} non-photo file(s): {}", dir.display(), others.len(), others.join(", ")));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photo(size: (u32, u32), model: &str) -> Photo {
        let (make, model) = (Some("Acme".to_string()), Some(model.to_string()));
        Photo { source: String::new(), file: String::new(), orientation: 1, taken: None, size, make, model, focal_mm: Some(4.2) }
    }

    #[test]
    fn two_phones_of_one_size_are_two_cameras() {
        let ph = [photo((64, 48), "Phone 1"), photo((64, 48), "Phone 2"), photo((64, 48), "Phone 1"), photo((48, 64), "Phone 1")];
        let (groups, of) = camera_groups(&ph);
        let folders: Vec<&str> = groups.iter().map(|g| g.folder.as_str()).collect();
        assert_eq!(folders, ["48x64", "64x48-1", "64x48-2"]);
        assert_eq!(of, [1, 2, 1, 0]);
        assert_eq!(groups.iter().map(|g| g.photos).collect::<Vec<_>>(), [1, 2, 1]);
        // Another focal length (a zoom) is another camera too; no EXIF at all is one device.
        let mut zoom = photo((64, 48), "Phone 1");
        zoom.focal_mm = Some(6.0);
        assert_eq!(camera_groups(&[photo((64, 48), "Phone 1"), zoom]).0.len(), 2);
        let bare = Photo { make: None, model: None, focal_mm: None, ..photo((64, 48), "") };
        let (groups, of) = camera_groups(&[bare.clone(), bare]);
        assert_eq!((groups.len(), groups[0].folder.as_str(), of), (1, "64x48", vec![0, 0]));
    }

    #[test]
    fn listing_keeps_photos_and_names_the_rest() {
        let d = tempfile::tempdir().unwrap();
        for f in ["b.JPG", "a.png", "notes.txt", ".hidden", "c.jpeg"] {
            std::fs::write(d.path().join(f), b"x").unwrap();
        }
        std::fs::create_dir(d.path().join("sub")).unwrap();
        let (p, o) = list(d.path()).unwrap();
        let names: Vec<_> = p.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["a.png", "b.JPG", "c.jpeg"]);
        assert_eq!(o, ["notes.txt"]);
    }
}
