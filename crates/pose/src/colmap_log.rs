//! What COLMAP's own log lines say: progress (`Processed file [i/N]`, `Matching image [i/N]`, `Matching block
//! [i/N, j/M]`, `Registering image #k (n)`, `Undistorting image [i/N]`) and the figures the report needs
//! (`Loading matches... M`, `Mean reprojection error: e px`). 3.8 prints bare lines; 3.13 and later print them
//! through glog (`I20251202 10:11:12.345 123 file.cc:261] Processed file [1/24]`), renamed matching progress
//! `Processing image/block` and the mapper's count `(num_reg_frames=n)`, and put the count of `Loading
//! matches...` on the next line. Every pattern is searched anywhere in a line, so both forms parse.

/// `[i/N]` right after `key`, as (i, N).
fn bracket_pair(line: &str, key: &str) -> Option<(u64, u64)> {
    let rest = &line[line.find(key)? + key.len()..];
    let rest = rest.trim_start().strip_prefix('[')?;
    let end = rest.find(']')?;
    let inner = &rest[..end];
    let first = inner.split(',').next()?;
    let (i, n) = first.split_once('/')?;
    Some((i.trim().parse().ok()?, n.trim().parse().ok()?))
}

/// Progress of a block matcher, `[i/N, j/M]` → blocks done of N·M.
fn block_progress(line: &str, key: &str) -> Option<(u64, u64)> {
    let rest = &line[line.find(key)? + key.len()..];
    let rest = rest.trim_start().strip_prefix('[')?;
    let inner = &rest[..rest.find(']')?];
    let mut parts = inner.split(',').map(|p| p.trim().split_once('/'));
    let (i, n) = parts.next()??;
    let (i, n): (u64, u64) = (i.parse().ok()?, n.parse().ok()?);
    match parts.next() {
        Some(Some((j, m))) => {
            let (j, m): (u64, u64) = (j.parse().ok()?, m.parse().ok()?);
            Some(((i.saturating_sub(1)) * m + j, n * m))
        }
        _ => Some((i, n)),
    }
}

/// Progress of the feature extractor: files processed of all.
pub fn extraction_progress(line: &str) -> Option<(u64, u64)> {
    bracket_pair(line, "Processed file")
}

/// Progress of a matcher: images or blocks done of all.
pub fn matching_progress(line: &str) -> Option<(u64, u64)> {
    bracket_pair(line, "Matching image")
        .or_else(|| bracket_pair(line, "Processing image"))
        .or_else(|| block_progress(line, "Matching block"))
        .or_else(|| block_progress(line, "Processing block"))
}

pub fn undistortion_progress(line: &str) -> Option<(u64, u64)> {
    bracket_pair(line, "Undistorting image")
}

/// The mapper's `Registering image #k (n)`: n images in the model being built, this one included.
pub fn registered_count(line: &str) -> Option<u64> {
    let rest = &line[line.find("Registering image #")? + "Registering image #".len()..];
    let open = rest.find('(')?;
    let inner = &rest[open + 1..open + rest[open..].find(')')?];
    let digits = inner.rsplit('=').next()?.trim();
    digits.parse().ok()
}

/// A new model is started (`Initializing with image pair #a and #b`): it holds 2 images.
pub fn starts_model(line: &str) -> bool {
    line.contains("Initializing with image pair")
}

/// Reads the mapper's `Loading matches... M` (M image pairs with verified matches) and `Loading images... N
/// (connected C)`, in either log form.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct MapperLog {
    pub matched_pairs: Option<u64>,
    pub images: Option<u64>,
    pub connected: Option<u64>,
    pending: Option<&'static str>,
    pub no_initial_pair: bool,
}

fn leading_number(s: &str) -> Option<u64> {
    let d: String = s.trim_start().chars().take_while(char::is_ascii_digit).collect();
    d.parse().ok()
}

/// The text after glog's `] ` prefix, or the whole line.
fn message(line: &str) -> &str {
    match line.find("] ") {
        Some(i) if line.starts_with(['I', 'W', 'E', 'F']) && line[..i].contains(':') => &line[i + 2..],
        _ => line,
    }
}

impl MapperLog {
    pub fn feed(&mut self, line: &str) {
        let msg = message(line);
        if msg.contains("No good initial image pair found") {
            self.no_initial_pair = true;
        }
        for key in ["Loading matches...", "Loading images..."] {
            if let Some(i) = msg.find(key) {
                let after = &msg[i + key.len()..];
                if after.trim().is_empty() {
                    self.pending = Some(key);
                } else {
                    self.set(key, after);
                }
                return;
            }
        }
        if let Some(key) = self.pending.take() {
            self.set(key, msg);
        }
    }

    fn set(&mut self, key: &str, after: &str) {
        let n = leading_number(after);
        if key == "Loading matches..." {
            self.matched_pairs = n;
        } else {
            self.images = n;
            self.connected = after.find("connected").and_then(|i| leading_number(&after[i + "connected".len()..]));
        }
    }
}

/// `Mean reprojection error: 0.51px` (model_analyzer).
pub fn mean_reprojection_error(text: &str) -> Option<f64> {
    let line = text.lines().find(|l| l.contains("Mean reprojection error"))?;
    let after = line.split("Mean reprojection error").nth(1)?.trim_start_matches([':', ' ']);
    let num: String = after.chars().take_while(|c| c.is_ascii_digit() || *c == '.' || *c == 'e' || *c == '-').collect();
    num.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    const GLOG: &str = "I20251202 10:11:12.345678 140 feature_extraction.cc:261] ";

    #[test]
    fn progress_in_both_log_forms() {
        assert_eq!(extraction_progress("Processed file [3/24]"), Some((3, 24)));
        assert_eq!(extraction_progress(&format!("{GLOG}Processed file [3/24]")), Some((3, 24)));
        assert_eq!(matching_progress("Matching image [7/24] in 0.5s"), Some((7, 24)));
        assert_eq!(matching_progress(&format!("{GLOG}Processing image [7/24]")), Some((7, 24)));
        // Blocks: [i/N, j/M] is block (i-1)·M + j of N·M.
        assert_eq!(matching_progress("Matching block [1/3, 1/3] in 2.0s"), Some((1, 9)));
        assert_eq!(matching_progress("Matching block [2/3, 3/3] in 2.0s"), Some((6, 9)));
        assert_eq!(matching_progress(&format!("{GLOG}Processing block [3/3, 3/3]")), Some((9, 9)));
        assert_eq!(matching_progress("Matching block [4/10]"), Some((4, 10)));
        assert_eq!(undistortion_progress("Undistorting image [5/60]"), Some((5, 60)));
        assert_eq!(registered_count("Registering image #6 (3)"), Some(3));
        assert_eq!(registered_count(&format!("{GLOG}Registering image #12 (num_reg_frames=17)")), Some(17));
        assert!(starts_model("Initializing with image pair #4 and #5"));
        for junk in ["", "Processed file", "Processed file [x/24]", "Matching image [3]", "Registering image #3"] {
            assert_eq!(extraction_progress(junk).or(matching_progress(junk)), None, "{junk}");
            assert_eq!(registered_count(junk), None, "{junk}");
        }
    }

    #[test]
    fn mapper_counts_in_both_forms() {
        let mut m = MapperLog::default();
        for l in ["Loading cameras... 1 in 0.000s", "Loading matches... 21 in 0.000s", "Loading images... 24 in 0.001s (connected 19)"] {
            m.feed(l);
        }
        assert_eq!((m.matched_pairs, m.images, m.connected), (Some(21), Some(24), Some(19)));
        let mut m = MapperLog::default();
        for l in [
            "I1202 10:00:00.1 1 database_cache.cc:134] Loading matches...",
            "I1202 10:00:00.1 1 database_cache.cc:139]  0 in 0.002s",
            "I1202 10:00:00.1 1 database_cache.cc:155] Loading images...",
            "I1202 10:00:00.1 1 database_cache.cc:230]  5 in 0.000s (connected 0)",
            "I1202 10:00:00.2 1 incremental_pipeline.cc:50] => No good initial image pair found.",
        ] {
            m.feed(l);
        }
        assert_eq!((m.matched_pairs, m.images, m.connected, m.no_initial_pair), (Some(0), Some(5), Some(0), true));
    }

    #[test]
    fn reprojection_error() {
        assert_eq!(mean_reprojection_error("Points: 10\nMean reprojection error: 0.512345px\n"), Some(0.512345));
        assert_eq!(mean_reprojection_error("I1202 model.cc:467] Mean reprojection error: 1.5px"), Some(1.5));
        assert_eq!(mean_reprojection_error("nothing"), None);
    }
}
