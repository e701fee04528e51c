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
}

/// `DateTimeOriginal` (else `DateTime`) of raw EXIF bytes, as `YYYY:MM:DD HH:MM:SS` (sorts as text).
fn exif_time(raw: Vec<u8>) -> Option<String> {
    let ex = exif::Reader::new().read_raw(raw).ok()?;
    for tag in [exif::Tag::DateTimeOriginal, exif::Tag::DateTime] {
        if let Some(f) = ex.get_field(tag, exif::In::PRIMARY) {
            if let exif::Value::Ascii(v) = &f.value {
                if let Some(s) = v.first() {
                    let s = String::from_utf8_lossy(s).trim().to_string();
                    if !s.is_empty() {
                        return Some(s);
                    }
                }
            }
        }
    }
    None
}

struct Decoded {
    img: DynamicImage,
    orientation: u8,
    taken: Option<String>,
}

fn decode(p: &Path) -> Result<Decoded, PoseError> {
    let bad = |msg: String| PoseError::input(p, format!("cannot decode this photo ({msg}); remove it or replace it with a readable JPEG/PNG"));
    let len = std::fs::metadata(p).map_err(|e| PoseError::io(p, e))?.len();
    let reader = ImageReader::open(p).map_err(|e| PoseError::io(p, e))?.with_guessed_format().map_err(|e| bad(e.to_string()))?;
    let mut dec = mvsplat360_dataset::image::limited_decoder(reader, len).map_err(bad)?;
    let orient = dec.orientation().unwrap_or(image::metadata::Orientation::NoTransforms);
    let taken = dec.exif_metadata().ok().flatten().and_then(exif_time);
    let mut img = DynamicImage::from_decoder(dec).map_err(|e| bad(e.to_string()))?;
    img.apply_orientation(orient);
    Ok(Decoded { img, orientation: orient.to_exif(), taken })
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
            .and_then(exif_time);
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
        out.push(Photo { source, file, orientation: d.orientation, taken: d.taken, size: (tw, th) });
        progress.set(k as u64 + 1);
    }
    progress.end();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

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
