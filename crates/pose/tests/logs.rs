//! The log parsing on COLMAP 3.8's own logs (recorded on the test scene; see data/logs/README.md).

use mvsplat360_pose::colmap_log::{self, MapperLog};

fn log(name: &str) -> String {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/logs").join(name);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn last<T>(text: &str, f: impl Fn(&str) -> Option<T>) -> (usize, Option<T>) {
    let hits: Vec<T> = text.lines().filter_map(f).collect();
    (hits.len(), hits.into_iter().last())
}

#[test]
fn extraction_and_matching_progress_reach_the_end() {
    assert_eq!(last(&log("feature_extractor.log"), colmap_log::extraction_progress), (24, Some((24, 24))));
    assert_eq!(last(&log("sequential_matcher.log"), colmap_log::matching_progress), (24, Some((24, 24))));
    // 24 images fit one exhaustive block.
    assert_eq!(last(&log("exhaustive_matcher.log"), colmap_log::matching_progress), (1, Some((1, 1))));
    assert_eq!(last(&log("image_undistorter.log"), colmap_log::undistortion_progress), (24, Some((24, 24))));
}

#[test]
fn mapper_of_a_posed_scene() {
    let text = log("mapper.log");
    let mut m = MapperLog::default();
    text.lines().for_each(|l| m.feed(l));
    assert_eq!((m.matched_pairs, m.images, m.connected), (Some(91), Some(24), Some(24)));
    // Registration counts climb to every image (the pair it starts from holds 2).
    let counts: Vec<u64> = text.lines().filter_map(colmap_log::registered_count).collect();
    assert_eq!(counts.iter().max(), Some(&24));
    assert_eq!(counts.first(), Some(&3));
    assert!(text.lines().any(colmap_log::starts_model));
    assert_eq!(colmap_log::mean_reprojection_error(&log("model_analyzer.log")), Some(0.250655));
}

#[test]
fn mapper_of_five_views_far_apart() {
    let mut m = MapperLog::default();
    log("mapper-fail.log").lines().for_each(|l| m.feed(l));
    assert_eq!((m.matched_pairs, m.images, m.connected, m.no_initial_pair), (Some(2), Some(5), Some(3), true));
}
