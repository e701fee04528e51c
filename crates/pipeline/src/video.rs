//! MP4 (H.264) output of the `render` command: `video.mp4` and the `compare.mp4` strip.
//!
//! Encoding uses Cisco's OpenH264 (BSD-2-Clause, compiled from source by the `openh264` crate) and muxing the
//! `mp4` crate (MIT). The stream is Constrained Baseline (what OpenH264 emits), the most widely decodable H.264
//! profile, and the file is laid out `ftyp, moov, mdat` ("fast start") so a browser can begin playing it
//! before the whole file has arrived.

use std::fmt;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use openh264::encoder::{ColorPrimaries, Encoder, EncoderConfig, FrameRate, IntraFramePeriod, QpRange, RateControlMode, TransferCharacteristics, VuiConfig};
use openh264::formats::YUVBuffer;
use openh264::OpenH264API;

/// An 8-bit RGB frame, row-major, width*height*3 bytes.
#[derive(Clone, PartialEq, Eq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Frame {
    /// An all-black frame.
    pub fn black(width: u32, height: u32) -> Self {
        Frame { width, height, rgb: vec![0; width as usize * height as usize * 3] }
    }

    /// The RGB triple at (x, y); `None` outside the frame or if `rgb` is too short.
    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = (y as usize * self.width as usize + x as usize) * 3;
        self.rgb.get(i..i + 3).map(|p| [p[0], p[1], p[2]])
    }
}

// Printing megabytes of pixels helps nobody.
impl fmt::Debug for Frame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Frame {{ {}x{}, {} bytes }}", self.width, self.height, self.rgb.len())
    }
}

/// Why a video could not be written. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("cannot write video {path}: no frames to encode")]
    NoFrames { path: PathBuf },
    #[error("cannot write video {path}: frame rate must be 1..={max} fps, got {fps}", max = MAX_FPS)]
    BadFps { path: PathBuf, fps: u32 },
    #[error("cannot write video {path}: frame {index} is {width}x{height} with {len} bytes (expected a non-empty frame of width*height*3 bytes)")]
    BadFrame { path: PathBuf, index: usize, width: u32, height: u32, len: usize },
    #[error("cannot write video {path}: frame {index} is {got_w}x{got_h} but frame 0 is {want_w}x{want_h}; all frames must have the same size")]
    SizeMismatch { path: PathBuf, index: usize, want_w: u32, want_h: u32, got_w: u32, got_h: u32 },
    #[error("cannot write video {path}: {width}x{height} frames exceed the H.264 encoder's limit of 3840x2160 (either orientation)")]
    TooLarge { path: PathBuf, width: u32, height: u32 },
    #[error("cannot write video {path}: H.264 encoding failed at frame {index}: {msg}")]
    Encode { path: PathBuf, index: usize, msg: String },
    #[error("cannot write video {path}: MP4 muxing failed: {msg}")]
    Mux { path: PathBuf, msg: String },
    #[error("cannot write video {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

/// Highest accepted frame rate; keeps `fps * TICKS_PER_FRAME` far from u32 overflow.
pub const MAX_FPS: u32 = 1000;

/// Media timescale is `fps * TICKS_PER_FRAME`, so every frame lasts exactly `TICKS_PER_FRAME` ticks and the
/// track duration is exact for any integer fps (a 1000 Hz timescale would round 1/30 s).
const TICKS_PER_FRAME: u32 = 1000;

/// Quality is set by QP, not bitrate. The crate cannot set OpenH264's fixed QP (its "RC off" mode pins QP 26),
/// so we use the buffer-based mode, which ignores the bit budget and walks QP down to QP_MIN within
/// [QP_MIN, QP_MAX], i.e. near-constant QP 16. Measured on a 448x256 photo pan at 30 fps: 40.8 dB RGB PSNR
/// against a 43.5 dB ceiling set by 4:2:0 chroma alone, ~0.75 Mbit/s; QP 20 gives 38.6 dB, QP 24 35.9 dB.
/// Quality/bitrate modes were avoided: with frame skipping off (which we need) OpenH264 warns on stderr.
const QP_MIN: u8 = 16;
const QP_MAX: u8 = 18;
/// Bit budget in bits per pixel per frame: in buffer-based mode it only seeds the first QP and the level
/// OpenH264 signals (e.g. 3.4 Mbit/s budget → level 2.1 for 448x256@30).
const BITS_PER_PIXEL: f64 = 1.0;
/// One IDR every this many seconds, so browsers can seek without decoding from the start.
const IDR_INTERVAL_S: u32 = 2;

/// Encode frames (all the same size) as H.264 in an MP4 container at `fps`. Writes `path` directly (the
/// caller handles temp-name + rename).
///
/// H.264 4:2:0 needs even dimensions: an odd width or height is padded by one column/row that repeats the
/// last one, so the video is then 1 pixel wider/taller than the frames. Colour is BT.601 limited range,
/// signalled in the SPS (VUI) together with sRGB primaries/transfer, which is what the frames are.
pub fn write_mp4(path: &Path, frames: &[Frame], fps: u32) -> Result<(), VideoError> {
    let bytes = encode_mp4(path, frames, fps)?;
    std::fs::write(path, bytes).map_err(|source| VideoError::Io { path: path.to_path_buf(), source })
}

/// Frames placed left to right (heights may differ: pad to the tallest with black), for gsplat | final | GT
/// comparisons. Frames are top-aligned. No frames gives a 0x0 frame. A frame whose `rgb` is shorter than
/// width*height*3 contributes black for the missing pixels.
pub fn side_by_side(frames: &[&Frame]) -> Frame {
    let width = frames.iter().fold(0u32, |w, f| w.saturating_add(f.width));
    let height = frames.iter().map(|f| f.height).max().unwrap_or(0);
    let mut out = Frame::black(width, height);
    let out_row = width as usize * 3;
    let mut x0 = 0usize;
    for f in frames {
        let row = f.width as usize * 3;
        for y in 0..f.height as usize {
            let (Some(src), Some(dst)) = (f.rgb.get(y * row..(y + 1) * row), out.rgb.get_mut(y * out_row + x0 * 3..y * out_row + x0 * 3 + row)) else {
                break;
            };
            dst.copy_from_slice(src);
        }
        x0 += f.width as usize;
    }
    out
}

/// One encoded frame in MP4 form (length-prefixed NAL units).
struct Sample {
    data: Vec<u8>,
    ticks: u32,
    sync: bool,
}

/// Encode and mux into memory; `path` is only used in error messages.
pub fn encode_mp4(path: &Path, frames: &[Frame], fps: u32) -> Result<Vec<u8>, VideoError> {
    let p = || path.to_path_buf();
    if !(1..=MAX_FPS).contains(&fps) {
        return Err(VideoError::BadFps { path: p(), fps });
    }
    let first = frames.first().ok_or_else(|| VideoError::NoFrames { path: p() })?;
    for (index, f) in frames.iter().enumerate() {
        let want = f.width as usize * f.height as usize * 3;
        if f.width == 0 || f.height == 0 || f.rgb.len() != want {
            return Err(VideoError::BadFrame { path: p(), index, width: f.width, height: f.height, len: f.rgb.len() });
        }
        if (f.width, f.height) != (first.width, first.height) {
            return Err(VideoError::SizeMismatch { path: p(), index, want_w: first.width, want_h: first.height, got_w: f.width, got_h: f.height });
        }
    }
    let pw = first.width as usize + (first.width as usize & 1);
    let ph = first.height as usize + (first.height as usize & 1);
    // OpenH264's own limit (level 5.2); checked here for a clear message. It also keeps the avc1 box's
    // 16-bit sizes in range.
    let (w16, h16) = match (u16::try_from(pw), u16::try_from(ph)) {
        (Ok(w), Ok(h)) if w.max(h) <= 3840 && w.min(h) <= 2160 => (w, h),
        _ => return Err(VideoError::TooLarge { path: p(), width: first.width, height: first.height }),
    };

    let bitrate = (pw as f64 * ph as f64 * fps as f64 * BITS_PER_PIXEL).min(u32::MAX as f64 / 2.0) as u32;
    let config = EncoderConfig::new()
        .rate_control_mode(RateControlMode::Bufferbased)
        .bitrate(openh264::encoder::BitRate::from_bps(bitrate))
        .max_frame_rate(FrameRate::from_hz(fps as f32))
        // Every input frame must become a sample, or timing and frame count drift.
        .skip_frames(false)
        .qp(QpRange::new(QP_MIN, QP_MAX))
        .intra_frame_period(IntraFramePeriod::from_num_frames(fps.saturating_mul(IDR_INTERVAL_S)))
        // Single thread: identical input gives an identical file.
        .num_threads(1)
        // IDRs exactly every IDR_INTERVAL_S; a scene-cut IDR buys nothing at a fixed QP on smooth camera paths.
        .scene_change_detect(false)
        .vui(VuiConfig::bt601().color_primaries(ColorPrimaries::Bt709).transfer_characteristics(TransferCharacteristics::Srgb));
    let mut encoder =
        Encoder::with_api_config(OpenH264API::from_source(), config).map_err(|e| VideoError::Encode { path: p(), index: 0, msg: e.to_string() })?;

    let mut sps: Option<Vec<u8>> = None;
    let mut pps: Option<Vec<u8>> = None;
    let mut samples: Vec<Sample> = Vec::with_capacity(frames.len());
    for (index, f) in frames.iter().enumerate() {
        let enc_err = |msg: String| VideoError::Encode { path: p(), index, msg };
        let mut yuv = vec![0u8; pw * ph * 3 / 2];
        rgb_to_i420(f, pw, ph, &mut yuv);
        let buf = YUVBuffer::from_vec(yuv, pw, ph);
        let stream = encoder.encode(&buf).map_err(|e| enc_err(e.to_string()))?;
        let mut data = Vec::new();
        let mut sync = false;
        for l in 0..stream.num_layers() {
            let Some(layer) = stream.layer(l) else { continue };
            for n in 0..layer.nal_count() {
                let Some(nal) = layer.nal_unit(n).and_then(strip_start_code) else { continue };
                let Some(&header) = nal.first() else { continue };
                match header & 0x1f {
                    // Parameter sets live in the avcC box; OpenH264 repeats them at each IDR with the same ids,
                    // so a change would mean the single avcC no longer describes the stream.
                    7 => keep_param_set(&mut sps, nal).map_err(|()| enc_err("the SPS changed mid-stream".into()))?,
                    8 => keep_param_set(&mut pps, nal).map_err(|()| enc_err("the PPS changed mid-stream".into()))?,
                    // Access unit delimiters carry nothing an MP4 sample needs.
                    9 => {}
                    t => {
                        sync |= t == 5;
                        let len = u32::try_from(nal.len()).map_err(|_| enc_err("NAL unit over 4 GiB".into()))?;
                        data.extend_from_slice(&len.to_be_bytes());
                        data.extend_from_slice(nal);
                    }
                }
            }
        }
        if data.is_empty() {
            // A skipped frame (should not happen with skipping off) holds the previous picture on screen.
            match samples.last_mut() {
                Some(prev) => prev.ticks += TICKS_PER_FRAME,
                None => return Err(enc_err("the encoder produced no picture for the first frame".into())),
            }
        } else {
            samples.push(Sample { data, ticks: TICKS_PER_FRAME, sync });
        }
    }
    // avcC copies profile/compatibility/level from SPS bytes 1..=3.
    let (Some(sps), Some(pps)) = (sps.filter(|s| s.len() >= 4), pps) else {
        return Err(VideoError::Encode { path: p(), index: 0, msg: "the encoder produced no usable SPS/PPS".into() });
    };
    if !samples.first().is_some_and(|s| s.sync) {
        return Err(VideoError::Encode { path: p(), index: 0, msg: "the first frame is not an IDR picture".into() });
    }

    mux(samples, sps, pps, w16, h16, fps * TICKS_PER_FRAME).map_err(|msg| VideoError::Mux { path: p(), msg })
}

fn keep_param_set(slot: &mut Option<Vec<u8>>, nal: &[u8]) -> Result<(), ()> {
    match slot {
        Some(prev) if prev.as_slice() != nal => Err(()),
        Some(_) => Ok(()),
        None => {
            *slot = Some(nal.to_vec());
            Ok(())
        }
    }
}

/// OpenH264 emits Annex B units (`00 00 00 01` or `00 00 01` then the NAL); MP4 wants the bare NAL.
fn strip_start_code(unit: &[u8]) -> Option<&[u8]> {
    let zeros = unit.iter().take_while(|&&b| b == 0).count();
    (zeros >= 2 && unit.get(zeros) == Some(&1)).then(|| &unit[zeros + 1..]).filter(|n| !n.is_empty())
}

/// BT.601 limited-range RGB → I420, padding odd sizes by edge replication. Done here rather than with the
/// crate's converter because that one truncates instead of rounding (luma half a code value dark) and needs
/// an already-even image.
fn rgb_to_i420(f: &Frame, pw: usize, ph: usize, out: &mut [u8]) {
    let (w, h) = (f.width as usize, f.height as usize);
    let px = |x: usize, y: usize| -> [f32; 3] {
        let i = (y.min(h - 1) * w + x.min(w - 1)) * 3;
        [f.rgb[i] as f32, f.rgb[i + 1] as f32, f.rgb[i + 2] as f32]
    };
    let (yp, uv) = out.split_at_mut(pw * ph);
    let (up, vp) = uv.split_at_mut(pw * ph / 4);
    for y in 0..ph {
        for x in 0..pw {
            let [r, g, b] = px(x, y);
            yp[y * pw + x] = to_u8(16.0 + (65.481 * r + 128.553 * g + 24.966 * b) / 255.0);
        }
    }
    // Chroma of the 2x2 mean (centre-sited), the usual choice for 4:2:0 from full-resolution RGB.
    for cy in 0..ph / 2 {
        for cx in 0..pw / 2 {
            let mut s = [0f32; 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = px(2 * cx + dx, 2 * cy + dy);
                for c in 0..3 {
                    s[c] += p[c] * 0.25;
                }
            }
            let [r, g, b] = s;
            up[cy * (pw / 2) + cx] = to_u8(128.0 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255.0);
            vp[cy * (pw / 2) + cx] = to_u8(128.0 + (112.0 * r - 93.786 * g - 18.214 * b) / 255.0);
        }
    }
}

fn to_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// Mux samples into an MP4 in memory, then move `moov` in front of `mdat`.
fn mux(samples: Vec<Sample>, sps: Vec<u8>, pps: Vec<u8>, width: u16, height: u16, timescale: u32) -> Result<Vec<u8>, String> {
    let brand = |s: &str| s.parse::<mp4::FourCC>().map_err(|e| e.to_string());
    let config = mp4::Mp4Config {
        major_brand: brand("isom")?,
        minor_version: 512,
        compatible_brands: vec![brand("isom")?, brand("iso2")?, brand("avc1")?, brand("mp41")?],
        timescale,
    };
    let mut w = mp4::Mp4Writer::write_start(Cursor::new(Vec::new()), &config).map_err(|e| e.to_string())?;
    w.add_track(&mp4::TrackConfig {
        track_type: mp4::TrackType::Video,
        timescale,
        language: "und".into(),
        media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig { width, height, seq_param_set: sps, pic_param_set: pps }),
    })
    .map_err(|e| e.to_string())?;
    let mut t = 0u64;
    for s in samples {
        let sample = mp4::Mp4Sample { start_time: t, duration: s.ticks, rendering_offset: 0, is_sync: s.sync, bytes: s.data.into() };
        w.write_sample(1, &sample).map_err(|e| e.to_string())?;
        t += sample.duration as u64;
    }
    w.write_end().map_err(|e| e.to_string())?;
    faststart(w.into_writer().into_inner())
}

/// Top-level box: type and byte range.
struct TopBox {
    kind: [u8; 4],
    start: usize,
    end: usize,
}

fn top_level_boxes(file: &[u8]) -> Result<Vec<TopBox>, String> {
    let mut out = Vec::new();
    let mut pos = 0usize;
    while pos < file.len() {
        let head = file.get(pos..pos + 8).ok_or("truncated box header")?;
        let size32 = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as u64;
        let kind = [head[4], head[5], head[6], head[7]];
        let size = match size32 {
            0 => (file.len() - pos) as u64,
            1 => {
                let l = file.get(pos + 8..pos + 16).ok_or("truncated large box header")?;
                u64::from_be_bytes([l[0], l[1], l[2], l[3], l[4], l[5], l[6], l[7]])
            }
            s => s,
        };
        let end = usize::try_from(size).ok().and_then(|s| pos.checked_add(s)).filter(|&e| e <= file.len() && e >= pos + 8);
        let end = end.ok_or("box size runs past the end of the file")?;
        out.push(TopBox { kind, start: pos, end });
        pos = end;
    }
    Ok(out)
}

/// Rewrite `ftyp, mdat, moov` as `ftyp, moov, mdat` so playback can start before the download ends, fixing
/// on the way two header fields the `mp4` crate's writer leaves off-spec: `next_track_id` (must exceed every
/// track id) and the track flags (enabled | in movie | in preview, as ffmpeg writes). Chunk offsets all point
/// into `mdat`, which moves back by exactly the size of `moov`.
fn faststart(file: Vec<u8>) -> Result<Vec<u8>, String> {
    use mp4::{Mp4Box, WriteBox};
    let boxes = top_level_boxes(&file)?;
    let moov_at = boxes.iter().position(|b| &b.kind == b"moov").ok_or("no moov box")?;
    let mdat_at = boxes.iter().position(|b| &b.kind == b"mdat").ok_or("no mdat box")?;
    if moov_at < mdat_at {
        return Ok(file);
    }
    let mut moov = mp4::Mp4Reader::read_header(Cursor::new(&file), file.len() as u64).map_err(|e| e.to_string())?.moov;
    moov.mvhd.next_track_id = moov.traks.iter().map(|t| t.tkhd.track_id).max().unwrap_or(0) + 1;
    for trak in &mut moov.traks {
        trak.tkhd.flags = 0x7;
        trak.tkhd.volume = mp4::FixedPointU8::new(0);
    }
    let delta = moov.box_size();
    for trak in &mut moov.traks {
        let stbl = &mut trak.mdia.minf.stbl;
        if let Some(stco) = stbl.stco.as_mut() {
            for e in &mut stco.entries {
                *e = u32::try_from(*e as u64 + delta).map_err(|_| "chunk offset over 4 GiB")?;
            }
        }
        if let Some(co64) = stbl.co64.as_mut() {
            for e in &mut co64.entries {
                *e += delta;
            }
        }
    }
    let mut out = Vec::with_capacity(file.len());
    for (i, b) in boxes.iter().enumerate() {
        if i == mdat_at {
            moov.write_box(&mut out).map_err(|e| e.to_string())?;
        }
        if i != moov_at {
            out.extend_from_slice(&file[b.start..b.end]);
        }
    }
    // A moov that re-serialises to a different size than box_size() promised would shift every offset.
    let old_moov = boxes[moov_at].end - boxes[moov_at].start;
    if out.len() as u64 != file.len() as u64 - old_moov as u64 + delta {
        return Err(format!("fast-start rewrite produced {} bytes, expected {}", out.len(), file.len() as u64 - old_moov as u64 + delta));
    }
    Ok(out)
}
