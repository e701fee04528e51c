//! MP4 output: the file is read back with the `mp4` crate and the H.264 decoded with OpenH264's decoder, so
//! the checks see what a player sees (container fields, timing, sync samples, pixels, frame order).

use std::io::Cursor;
use std::path::Path;

use mvsplat360_pipeline::video::{side_by_side, write_mp4, Frame, VideoError};
use openh264::decoder::Decoder;
use openh264::formats::YUVSource;

/// Smooth moving colours: every frame differs, little chroma detail (so 4:2:0 costs little PSNR).
fn pattern(w: u32, h: u32, t: u32) -> Frame {
    let mut rgb = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            let (xf, yf, tf) = (x as f32, y as f32, t as f32);
            let r = 128.0 + 100.0 * ((xf + 3.0 * tf) / 7.0).sin();
            let g = 128.0 + 100.0 * ((yf - 2.0 * tf) / 9.0).cos();
            let b = 128.0 + 90.0 * ((xf + yf + 5.0 * tf) / 11.0).sin();
            rgb.extend([r, g, b].map(|v| v.round().clamp(0.0, 255.0) as u8));
        }
    }
    Frame { width: w, height: h, rgb }
}

/// Independent BT.601 limited-range YUV → RGB (textbook float form, rounded).
fn yuv_to_rgb(yuv: &impl YUVSource) -> (usize, usize, Vec<u8>) {
    let (w, h) = yuv.dimensions();
    let (sy, su, sv) = yuv.strides();
    let mut out = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let l = (yuv.y()[y * sy + x] as f64 - 16.0) * 255.0 / 219.0;
            let cb = (yuv.u()[(y / 2) * su + x / 2] as f64 - 128.0) * 255.0 / 224.0;
            let cr = (yuv.v()[(y / 2) * sv + x / 2] as f64 - 128.0) * 255.0 / 224.0;
            let r = l + 1.402 * cr;
            let g = l - 0.344136 * cb - 0.714136 * cr;
            let b = l + 1.772 * cb;
            out.extend([r, g, b].map(|v| v.round().clamp(0.0, 255.0) as u8));
        }
    }
    (w, h, out)
}

/// PSNR of `decoded` (dw wide) against `src` padded the way write_mp4 promises (edge replication), over the
/// decoded size.
fn psnr(src: &Frame, dw: usize, dh: usize, decoded: &[u8]) -> f64 {
    let (w, h) = (src.width as usize, src.height as usize);
    let mut se = 0f64;
    for y in 0..dh {
        for x in 0..dw {
            let s = (y.min(h - 1) * w + x.min(w - 1)) * 3;
            for c in 0..3 {
                let d = src.rgb[s + c] as f64 - decoded[(y * dw + x) * 3 + c] as f64;
                se += d * d;
            }
        }
    }
    let mse = se / (dw * dh * 3) as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0 * 255.0 / mse).log10()
    }
}

fn top_level_box_kinds(bytes: &[u8]) -> Vec<String> {
    let mut kinds = Vec::new();
    let mut pos = 0usize;
    while pos + 8 <= bytes.len() {
        let size = u32::from_be_bytes(bytes[pos..pos + 4].try_into().unwrap()) as usize;
        kinds.push(String::from_utf8_lossy(&bytes[pos + 4..pos + 8]).into_owned());
        assert!(size >= 8, "box size {size} at {pos}");
        pos += size;
    }
    assert_eq!(pos, bytes.len(), "boxes must tile the file exactly");
    kinds
}

struct ReadBack {
    width: u16,
    height: u16,
    samples: u32,
    duration_s: f64,
    movie_duration_s: f64,
    sync: Vec<bool>,
    idr: Vec<bool>,
    decoded: Vec<(usize, usize, Vec<u8>)>,
}

fn read_back(path: &Path) -> ReadBack {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(top_level_box_kinds(&bytes), ["ftyp", "moov", "mdat"], "fast-start layout");
    let mut mp4 = mp4::Mp4Reader::read_header(Cursor::new(&bytes), bytes.len() as u64).unwrap();
    assert_eq!(mp4.tracks().len(), 1, "exactly one track");
    assert!(mp4.moov.mvhd.next_track_id > 1, "next_track_id must exceed the track ids");
    let (&id, track) = mp4.tracks().iter().next().unwrap();
    assert_eq!(track.track_type().unwrap(), mp4::TrackType::Video);
    assert_eq!(track.media_type().unwrap(), mp4::MediaType::H264);
    let sps = track.sequence_parameter_set().unwrap().to_vec();
    let pps = track.picture_parameter_set().unwrap().to_vec();
    assert_eq!(sps[0] & 0x1f, 7);
    assert_eq!(pps[0] & 0x1f, 8);
    let avcc = &track.trak.mdia.minf.stbl.stsd.avc1.as_ref().unwrap().avcc;
    assert_eq!(
        (avcc.avc_profile_indication, avcc.profile_compatibility, avcc.avc_level_indication),
        (sps[1], sps[2], sps[3]),
        "avcC profile/level come from the SPS"
    );
    let (width, height, samples) = (track.width(), track.height(), track.sample_count());
    let duration_s = track.duration().as_secs_f64();
    let movie_duration_s = mp4.duration().as_secs_f64();

    let mut decoder = Decoder::new().unwrap();
    let (mut sync, mut idr, mut decoded) = (Vec::new(), Vec::new(), Vec::new());
    for i in 1..=samples {
        let s = mp4.read_sample(id, i).unwrap().unwrap();
        sync.push(s.is_sync);
        let mut annexb = Vec::new();
        if i == 1 {
            for ps in [&sps, &pps] {
                annexb.extend([0, 0, 0, 1]);
                annexb.extend_from_slice(ps);
            }
        }
        let mut is_idr = false;
        let mut rest = &s.bytes[..];
        while !rest.is_empty() {
            let len = u32::from_be_bytes(rest[..4].try_into().unwrap()) as usize;
            let nal = &rest[4..4 + len];
            assert!(!matches!(nal[0] & 0x1f, 7 | 8), "parameter sets belong in avcC");
            is_idr |= nal[0] & 0x1f == 5;
            annexb.extend([0, 0, 0, 1]);
            annexb.extend_from_slice(nal);
            rest = &rest[4 + len..];
        }
        idr.push(is_idr);
        let yuv = decoder.decode(&annexb).unwrap().expect("Baseline H.264 yields one picture per sample");
        decoded.push(yuv_to_rgb(&yuv));
    }
    ReadBack { width, height, samples, duration_s, movie_duration_s, sync, idr, decoded }
}

fn roundtrip(w: u32, h: u32, n: u32, fps: u32) -> ReadBack {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("out.mp4");
    let frames: Vec<Frame> = (0..n).map(|t| pattern(w, h, t)).collect();
    write_mp4(&path, &frames, fps).unwrap();
    let rb = read_back(&path);

    let (pw, ph) = (w + w % 2, h + h % 2);
    assert_eq!((rb.width as u32, rb.height as u32), (pw, ph), "odd sizes pad to even");
    assert_eq!(rb.samples, n, "one sample per frame");
    let want = n as f64 / fps as f64;
    assert!((rb.duration_s - want).abs() < 1e-3, "track duration {} vs {want}", rb.duration_s);
    assert!((rb.movie_duration_s - want).abs() < 1e-3, "movie duration {} vs {want}", rb.movie_duration_s);
    assert!(rb.sync[0], "first sample is a sync sample");
    assert_eq!(rb.sync, rb.idr, "sync-sample table matches the IDR pictures");

    for (k, (dw, dh, rgb)) in rb.decoded.iter().enumerate() {
        assert_eq!((*dw as u32, *dh as u32), (pw, ph));
        let p = psnr(&frames[k], *dw, *dh, rgb);
        assert!(p > 30.0, "{w}x{h} frame {k}: PSNR {p:.1} dB");
        // Frame order: each decoded picture matches its own input best.
        let best = (0..frames.len()).max_by(|&a, &b| psnr(&frames[a], *dw, *dh, rgb).total_cmp(&psnr(&frames[b], *dw, *dh, rgb))).unwrap();
        assert_eq!(best, k, "{w}x{h}: decoded frame {k} looks most like input {best}");
    }
    rb
}

#[test]
fn even_size_roundtrips() {
    roundtrip(64, 48, 10, 10);
}

#[test]
fn non_macroblock_size_roundtrips() {
    // Not a multiple of 16: the SPS must crop the coded picture back to 66x50.
    roundtrip(66, 50, 10, 24);
}

#[test]
fn odd_size_is_padded() {
    roundtrip(65, 49, 10, 30);
}

#[test]
fn long_video_has_periodic_sync_samples() {
    // 5 fps for 5 s: an IDR every 2 s (10 frames), so a browser can seek.
    let rb = roundtrip(32, 32, 25, 5);
    let at: Vec<usize> = rb.sync.iter().enumerate().filter(|(_, &s)| s).map(|(i, _)| i).collect();
    assert_eq!(at, [0, 10, 20]);
}

#[test]
fn errors_name_the_file_and_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.mp4");
    let f = pattern(16, 16, 0);

    let e = write_mp4(&path, &[], 30).unwrap_err();
    assert!(matches!(e, VideoError::NoFrames { .. }), "{e}");
    assert!(e.to_string().contains("bad.mp4") && e.to_string().contains("no frames"), "{e}");

    let e = write_mp4(&path, &[f.clone(), pattern(18, 16, 1)], 30).unwrap_err();
    assert!(matches!(e, VideoError::SizeMismatch { index: 1, .. }), "{e}");
    assert!(e.to_string().contains("bad.mp4") && e.to_string().contains("18x16"), "{e}");

    let short = Frame { width: 16, height: 16, rgb: vec![0; 10] };
    let e = write_mp4(&path, &[f.clone(), short], 30).unwrap_err();
    assert!(matches!(e, VideoError::BadFrame { index: 1, len: 10, .. }), "{e}");

    let empty = Frame { width: 0, height: 0, rgb: vec![] };
    let e = write_mp4(&path, &[empty], 30).unwrap_err();
    assert!(matches!(e, VideoError::BadFrame { index: 0, .. }), "{e}");

    let e = write_mp4(&path, std::slice::from_ref(&f), 0).unwrap_err();
    assert!(matches!(e, VideoError::BadFps { fps: 0, .. }), "{e}");

    let wide = Frame { width: 3842, height: 2, rgb: vec![0; 3842 * 2 * 3] };
    let e = write_mp4(&path, &[wide], 30).unwrap_err();
    assert!(matches!(e, VideoError::TooLarge { width: 3842, .. }), "{e}");

    assert!(!path.exists(), "nothing is written on error");

    let missing = dir.path().join("no/such/dir/x.mp4");
    let e = write_mp4(&missing, &[f], 30).unwrap_err();
    assert!(matches!(e, VideoError::Io { .. }), "{e}");
    assert!(e.to_string().contains("x.mp4"), "{e}");
}

#[test]
fn same_input_gives_same_file() {
    let dir = tempfile::tempdir().unwrap();
    let frames: Vec<Frame> = (0..4).map(|t| pattern(32, 16, t)).collect();
    let (a, b) = (dir.path().join("a.mp4"), dir.path().join("b.mp4"));
    write_mp4(&a, &frames, 30).unwrap();
    write_mp4(&b, &frames, 30).unwrap();
    assert_eq!(std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
}

#[test]
fn side_by_side_places_frames_and_pads_with_black() {
    let solid = |w: u32, h: u32, c: [u8; 3]| Frame { width: w, height: h, rgb: c.repeat((w * h) as usize) };
    let a = solid(2, 3, [255, 0, 0]);
    let b = solid(3, 1, [0, 255, 0]);
    let c = solid(1, 2, [0, 0, 255]);
    let s = side_by_side(&[&a, &b, &c]);
    assert_eq!((s.width, s.height, s.rgb.len()), (6, 3, 6 * 3 * 3));
    for y in 0..3 {
        for x in 0..6 {
            let want = match x {
                0..=1 => [255, 0, 0],
                2..=4 if y < 1 => [0, 255, 0],
                5 if y < 2 => [0, 0, 255],
                _ => [0, 0, 0],
            };
            assert_eq!(s.pixel(x, y), Some(want), "pixel ({x},{y})");
        }
    }
    // Pixel order within a frame survives (not just solid colours).
    let g = pattern(5, 4, 0);
    let s = side_by_side(&[&solid(2, 4, [9, 9, 9]), &g]);
    for y in 0..4 {
        for x in 0..5 {
            assert_eq!(s.pixel(x + 2, y), g.pixel(x, y));
        }
    }
    let empty = side_by_side(&[]);
    assert_eq!((empty.width, empty.height, empty.rgb.len()), (0, 0, 0));
}

#[test]
fn photo_pan_is_clean_and_compact() {
    // A render-like clip: a 448x256 camera pan over a real photo, 1 s at 30 fps.
    let img = image::open(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/woodbox/images/000.jpg")).unwrap().to_rgb8();
    let big = image::imageops::resize(&img, 560, 320, image::imageops::FilterType::CatmullRom);
    let frames: Vec<Frame> = (0..30u32)
        .map(|t| {
            let c = image::imageops::crop_imm(&big, t * 3, t * 2, 448, 256).to_image();
            Frame { width: 448, height: 256, rgb: c.into_raw() }
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pan.mp4");
    write_mp4(&path, &frames, 30).unwrap();
    let kbit = std::fs::metadata(&path).unwrap().len() as f64 * 8.0 / 1000.0;
    let rb = read_back(&path);
    let ps: Vec<f64> = rb.decoded.iter().enumerate().map(|(k, (w, h, d))| psnr(&frames[k], *w, *h, d)).collect();
    let mean = ps.iter().sum::<f64>() / ps.len() as f64;
    let min = ps.iter().cloned().fold(f64::INFINITY, f64::min);
    eprintln!("photo pan: {kbit:.0} kbit/s, PSNR mean {mean:.2} dB, min {min:.2} dB");
    // 4:2:0 alone caps this clip near 43.5 dB; QP 16-18 lands about 2.5 dB under it.
    assert!(mean > 39.0 && min > 38.0, "PSNR mean {mean:.2} min {min:.2}");
    assert!(kbit < 3000.0, "{kbit:.0} kbit/s for 448x256@30");
    assert_eq!(rb.sync, [vec![true], vec![false; 29]].concat(), "one IDR per 2 s");
}
