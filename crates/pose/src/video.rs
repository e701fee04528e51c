//! Frames from a video: ffprobe for the size, rotation, frame count and transfer function; one ffmpeg decode
//! (rotation applied, scaled, HDR tone-mapped) piped as raw RGB, of which the sharpest frame of each of N
//! equal intervals is kept. One pass, two frames in memory, however long the video.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};

use serde::Serialize;
use serde_json::Value;

use crate::error::PoseError;
use crate::Progress;

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VideoInfo {
    pub codec: String,
    /// Stored size, before rotation.
    pub width: u32,
    pub height: u32,
    /// Display rotation in degrees (a phone held upright records landscape pixels and a 90° tag).
    pub rotation: i32,
    pub frames: u64,
    /// `ffprobe`'s `nb_frames`, or counted by decoding (`-count_frames`) when the container has none.
    pub frame_count_source: String,
    pub pix_fmt: String,
    pub color_transfer: Option<String>,
}

impl VideoInfo {
    /// HLG (`arib-std-b67`) or PQ (`smpte2084`).
    pub fn hdr(&self) -> Option<&'static str> {
        match self.color_transfer.as_deref() {
            Some("arib-std-b67") => Some("HLG"),
            Some("smpte2084") => Some("PQ"),
            _ => None,
        }
    }

    /// The displayed size (rotation applied).
    pub fn display_size(&self) -> (u32, u32) {
        if self.rotation.rem_euclid(180) == 90 {
            (self.height, self.width)
        } else {
            (self.width, self.height)
        }
    }
}

fn ffprobe_json(ffprobe: &Path, args: &[&str], input: &Path) -> Result<Value, PoseError> {
    let out = Command::new(ffprobe)
        .args(["-v", "error", "-select_streams", "v:0"])
        .args(args)
        .args(["-of", "json"])
        .arg(input)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| PoseError::Engine { program: ffprobe.display().to_string(), msg: format!("cannot start it: {e}") })?;
    let err = String::from_utf8_lossy(&out.stderr).trim().to_string();
    if !out.status.success() {
        let why = if err.is_empty() { "ffprobe failed".to_string() } else { err };
        return Err(PoseError::input(
            input,
            format!("cannot read it as a video ({why}); give a video file ffmpeg reads (mp4, mov, mkv) or a folder of photos"),
        ));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| PoseError::Engine { program: ffprobe.display().to_string(), msg: format!("unreadable JSON: {e}") })
}

fn as_u64(v: Option<&Value>) -> Option<u64> {
    v.and_then(|v| v.as_u64().or_else(|| v.as_str().and_then(|s| s.parse().ok())))
}

/// Probes the first video stream.
pub fn probe(ffprobe: &Path, input: &Path) -> Result<VideoInfo, PoseError> {
    let v = ffprobe_json(
        ffprobe,
        &["-show_entries", "stream=codec_name,width,height,nb_frames,pix_fmt,color_transfer:stream_side_data=rotation:stream_tags=rotate"],
        input,
    )?;
    let s = v.get("streams").and_then(Value::as_array).and_then(|a| a.first()).cloned().unwrap_or(Value::Null);
    let (width, height) = match (as_u64(s.get("width")), as_u64(s.get("height"))) {
        (Some(w), Some(h)) if w > 0 && h > 0 => (w as u32, h as u32),
        _ => return Err(PoseError::input(input, "has no video stream; give a video file (mp4, mov, mkv) or a folder of photos")),
    };
    let side = s.get("side_data_list").and_then(Value::as_array).and_then(|l| l.iter().find_map(|d| d.get("rotation").and_then(Value::as_f64)));
    let tag = s.get("tags").and_then(|t| t.get("rotate")).and_then(|r| r.as_str().and_then(|x| x.parse::<f64>().ok()));
    let rotation = side.or(tag).unwrap_or(0.0).round() as i32;
    let (frames, frame_count_source) = match as_u64(s.get("nb_frames")).filter(|&n| n > 0) {
        Some(n) => (n, "nb_frames".to_string()),
        None => {
            let c = ffprobe_json(ffprobe, &["-count_frames", "-show_entries", "stream=nb_read_frames"], input)?;
            let n = as_u64(c.get("streams").and_then(Value::as_array).and_then(|a| a.first()).and_then(|s| s.get("nb_read_frames"))).unwrap_or(0);
            (n, "count_frames".to_string())
        }
    };
    if frames == 0 {
        return Err(PoseError::input(input, "its video stream has no decodable frames"));
    }
    Ok(VideoInfo {
        codec: s.get("codec_name").and_then(Value::as_str).unwrap_or("unknown").into(),
        width,
        height,
        rotation,
        frames,
        frame_count_source,
        pix_fmt: s.get("pix_fmt").and_then(Value::as_str).unwrap_or("unknown").into(),
        color_transfer: s.get("color_transfer").and_then(Value::as_str).map(String::from),
    })
}

/// Scale so the long side is at most `max_size` (never up), even sides for the decoder's chroma.
pub fn output_size((w, h): (u32, u32), max_size: u32) -> (u32, u32) {
    let long = w.max(h);
    if long <= max_size {
        return (w, h);
    }
    let s = max_size as f64 / long as f64;
    let even = |x: f64| ((x / 2.0).round() as u32 * 2).max(2);
    (even(w as f64 * s), even(h as f64 * s))
}

/// Frame `i` of `total` falls in interval ⌊i·n/total⌋ of `n` equal intervals.
pub fn interval_of(i: u64, total: u64, n: u64) -> u64 {
    if total == 0 {
        return 0;
    }
    ((i.min(total - 1) as u128 * n as u128) / total as u128) as u64
}

/// Variance of the 4-neighbour Laplacian of the luma: higher is sharper (motion blur and defocus lower it).
pub fn sharpness(rgb: &[u8], w: usize, h: usize) -> f64 {
    if w < 3 || h < 3 {
        return 0.0;
    }
    let luma: Vec<f32> = rgb.chunks_exact(3).map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32).collect();
    let (mut s, mut s2, mut n) = (0f64, 0f64, 0f64);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = y * w + x;
            let l = (luma[i - 1] + luma[i + 1] + luma[i - w] + luma[i + w] - 4.0 * luma[i]) as f64;
            s += l;
            s2 += l * l;
            n += 1.0;
        }
    }
    s2 / n - (s / n) * (s / n)
}

/// A frame kept.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct SampledFrame {
    pub file: String,
    /// Index in the decoded stream (0-based).
    pub source_frame: u64,
    pub sharpness: f64,
}

/// The video filter: HDR → SDR tone mapping when asked for and possible, then the scale.
fn filter_chain((w, h): (u32, u32), tonemap: bool) -> String {
    let scale = format!("scale={w}:{h}:flags=area");
    if tonemap {
        // Linear light, then Hable's curve into BT.709: the usual HDR→SDR route of ffmpeg's zimg filters.
        format!("zscale=t=linear:npl=100,format=gbrpf32le,zscale=p=bt709,tonemap=tonemap=hable:desat=0,zscale=t=bt709:m=bt709:r=tv,format=yuv420p,{scale}")
    } else {
        scale
    }
}

/// Whether this ffmpeg has the filters tone mapping needs (zscale needs libzimg).
pub fn can_tonemap(ffmpeg: &Path) -> bool {
    let out = Command::new(ffmpeg).args(["-hide_banner", "-filters"]).stdin(Stdio::null()).output();
    match out {
        Ok(o) => {
            let t = String::from_utf8_lossy(&o.stdout);
            let has = |f: &str| t.lines().any(|l| l.split_whitespace().nth(1) == Some(f));
            has("zscale") && has("tonemap")
        }
        Err(_) => false,
    }
}

/// What the extraction did, for the report.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Extraction {
    pub frames: Vec<SampledFrame>,
    pub decoded: u64,
    pub size: (u32, u32),
    /// `none`, `tone-mapped (HLG)`, or `not tone-mapped (PQ): …`.
    pub hdr: String,
    pub argv: Vec<String>,
    pub seconds: f64,
}

/// Decodes `input` once and writes the sharpest frame of each of `n` intervals as `frame_NNNNNN.png`
/// (NNNNNN = its index in the video) into `dir`. PNG, not JPEG: a second lossy compression of an already
/// compressed frame biased COLMAP's focal length (test video, 3 runs each, worst focal error: JPEG q95 4:2:2 as
/// the `image` crate writes it 2.3–3.5 %, PIL q95 1.3–2.1 %, PNG 0.7–0.9 %).
pub fn extract(ffmpeg: &Path, input: &Path, info: &VideoInfo, n: u64, max_size: u32, dir: &Path, progress: &dyn Progress) -> Result<Extraction, PoseError> {
    let t0 = std::time::Instant::now();
    let size = output_size(info.display_size(), max_size);
    let (hdr, tonemap) = match info.hdr() {
        None => ("none".to_string(), false),
        Some(kind) if can_tonemap(ffmpeg) => (format!("tone-mapped ({kind})"), true),
        Some(kind) => {
            let msg = format!("not tone-mapped ({kind}): this ffmpeg lacks the zscale/tonemap filters, so colours are flat; convert the video to SDR first for better matching");
            progress.note(&format!("warning: {}: HDR video {msg}", input.display()));
            (msg, false)
        }
    };
    let n = n.clamp(1, info.frames);
    let argv: Vec<String> = [ffmpeg.display().to_string(), "-nostdin".into(), "-v".into(), "error".into(), "-i".into(), input.display().to_string()]
        .into_iter()
        .chain(["-map".into(), "0:v:0".into(), "-vf".into(), filter_chain(size, tonemap)])
        .chain(["-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"].map(String::from))
        .collect();
    let mut child = crate::engine::spawn_grouped(&argv)?;
    let mut stderr = child.stderr.take();
    let err_thread = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(e) = stderr.as_mut() {
            let _ = e.read_to_string(&mut s);
        }
        s
    });
    let (w, h) = (size.0 as usize, size.1 as usize);
    let mut cur = vec![0u8; w * h * 3];
    let mut best: Option<(u64, f64, Vec<u8>)> = None;
    let mut kept = vec![];
    let mut decoded = 0u64;
    let mut stdout = child.stdout.take().ok_or_else(|| PoseError::Engine { program: argv[0].clone(), msg: "no output pipe".into() })?;
    progress.begin("frames", info.frames);
    let flush = |best: &mut Option<(u64, f64, Vec<u8>)>, kept: &mut Vec<SampledFrame>| -> Result<(), PoseError> {
        if let Some((i, s, px)) = best.take() {
            let file = format!("frame_{i:06}.png");
            write_png(&dir.join(&file), &px, size)?;
            kept.push(SampledFrame { file, source_frame: i, sharpness: s });
        }
        Ok(())
    };
    let mut result = Ok(());
    loop {
        match stdout.read_exact(&mut cur) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
            Err(e) => {
                result = Err(PoseError::Engine { program: argv[0].clone(), msg: format!("reading decoded frames: {e}") });
                break;
            }
        }
        let k = interval_of(decoded, info.frames, n);
        if best.as_ref().is_some_and(|b| interval_of(b.0, info.frames, n) != k) {
            if let Err(e) = flush(&mut best, &mut kept) {
                result = Err(e);
                break;
            }
        }
        let s = sharpness(&cur, w, h);
        match &mut best {
            Some(b) if b.1 >= s => {}
            Some(b) => {
                b.0 = decoded;
                b.1 = s;
                b.2.copy_from_slice(&cur);
            }
            None => best = Some((decoded, s, cur.clone())),
        }
        decoded += 1;
        progress.set(decoded.min(info.frames));
    }
    if result.is_err() {
        let _ = child.kill();
    }
    let status = crate::engine::wait_child(&mut child);
    let err_text = err_thread.join().unwrap_or_default();
    result?;
    flush(&mut best, &mut kept)?;
    progress.end();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) if crate::engine::was_stopped() => {
            return Err(PoseError::Engine { program: argv[0].clone(), msg: format!("stopped ({s})") });
        }
        Ok(s) => {
            return Err(PoseError::input(input, format!("ffmpeg could not decode it ({s}): {}", err_text.trim())));
        }
        Err(e) => return Err(PoseError::Engine { program: argv[0].clone(), msg: e.to_string() }),
    }
    if kept.is_empty() {
        return Err(PoseError::input(input, format!("ffmpeg decoded no frames: {}", err_text.trim())));
    }
    Ok(Extraction { frames: kept, decoded, size, hdr, argv, seconds: t0.elapsed().as_secs_f64() })
}

fn write_png(path: &Path, rgb: &[u8], (w, h): (u32, u32)) -> Result<(), PoseError> {
    use image::ImageEncoder;
    let f = std::fs::File::create(path).map_err(|e| PoseError::io(path, e))?;
    let enc = image::codecs::png::PngEncoder::new(std::io::BufWriter::new(f));
    enc.write_image(rgb, w, h, image::ExtendedColorType::Rgb8).map_err(|e| PoseError::io(path, std::io::Error::other(e)))
}

/// The folder the frames of `input` go to (for messages).
pub fn describe(info: &VideoInfo) -> String {
    let (w, h) = info.display_size();
    format!("{} video, {w}x{h}, {} frames{}", info.codec, info.frames, info.hdr().map(|k| format!(", HDR {k}")).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_split_evenly() {
        // 10 frames, 3 intervals: 0-3 | 4-6 | 7-9 (⌊i·3/10⌋).
        let ks: Vec<u64> = (0..10).map(|i| interval_of(i, 10, 3)).collect();
        assert_eq!(ks, [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]);
        // As many intervals as frames: every frame its own; frames past a wrong count stay in the last.
        assert!((0..60).all(|i| interval_of(i, 60, 60) == i));
        assert_eq!(interval_of(75, 60, 60), 59);
    }

    #[test]
    fn sizes_scale_the_long_side_and_keep_even() {
        assert_eq!(output_size((3840, 2160), 1000), (1000, 562));
        assert_eq!(output_size((2160, 3840), 1000), (562, 1000));
        assert_eq!(output_size((896, 512), 1000), (896, 512));
        assert_eq!(output_size((1001, 3), 1000), (1000, 2));
    }

    #[test]
    fn sharpness_ranks_blur_below_detail() {
        let (w, h) = (32, 24);
        let checker: Vec<u8> = (0..w * h).flat_map(|i| if (i % w / 2 + i / w / 2) % 2 == 0 { [255u8; 3] } else { [0u8; 3] }).collect();
        // A 3x3 box blur of the same pattern.
        let mut blurred = checker.clone();
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let mut s = 0u32;
                for dy in 0..3 {
                    for dx in 0..3 {
                        s += checker[((y + dy - 1) * w + x + dx - 1) * 3] as u32;
                    }
                }
                blurred[(y * w + x) * 3..(y * w + x) * 3 + 3].fill((s / 9) as u8);
            }
        }
        let flat = vec![128u8; w * h * 3];
        assert!(sharpness(&checker, w, h) > sharpness(&blurred, w, h));
        assert!(sharpness(&blurred, w, h) > 0.0);
        assert_eq!(sharpness(&flat, w, h), 0.0);
    }

    #[test]
    fn rotation_swaps_the_displayed_size() {
        let mut i = VideoInfo {
            codec: "h264".into(),
            width: 1920,
            height: 1080,
            rotation: -90,
            frames: 10,
            frame_count_source: "nb_frames".into(),
            pix_fmt: "yuv420p10le".into(),
            color_transfer: Some("arib-std-b67".into()),
        };
        assert_eq!(i.display_size(), (1080, 1920));
        assert_eq!(i.hdr(), Some("HLG"));
        i.rotation = 180;
        assert_eq!(i.display_size(), (1920, 1080));
    }
}
