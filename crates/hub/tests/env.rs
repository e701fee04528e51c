//! The environment read as the Python client reads it. The only test of its binary: it sets variables.

use mvsplat360_hub::HubConfig;

const VARS: &[&str] = &[
    "HF_ENDPOINT",
    "HF_HUB_CACHE",
    "HUGGINGFACE_HUB_CACHE",
    "HF_HOME",
    "XDG_CACHE_HOME",
    "HF_TOKEN",
    "HUGGING_FACE_HUB_TOKEN",
    "HF_TOKEN_PATH",
    "HF_HUB_OFFLINE",
    "TRANSFORMERS_OFFLINE",
];

fn clear() {
    for v in VARS {
        std::env::remove_var(v);
    }
}

#[test]
fn precedence_as_in_huggingface_hub() {
    let tmp = tempfile::tempdir().unwrap();
    let home = tmp.path().join("home");
    std::fs::create_dir_all(home.join(".cache/huggingface")).unwrap();
    clear();
    std::env::set_var("HOME", &home);

    let c = HubConfig::from_env();
    assert_eq!(c.endpoint, "https://huggingface.co");
    assert_eq!(c.cache_dir, home.join(".cache/huggingface/hub"));
    assert_eq!(c.token_path, home.join(".cache/huggingface/token"));
    assert_eq!(c.token, None);
    assert!(!c.offline);

    // The token file, trimmed.
    std::fs::write(home.join(".cache/huggingface/token"), "hf_file\n").unwrap();
    assert_eq!(HubConfig::from_env().token.as_deref(), Some("hf_file"));

    std::env::set_var("XDG_CACHE_HOME", tmp.path().join("xdg"));
    let c = HubConfig::from_env();
    assert_eq!(c.cache_dir, tmp.path().join("xdg/huggingface/hub"));
    assert_eq!(c.token, None, "the token file moves with XDG_CACHE_HOME");

    std::env::set_var("HF_HOME", "~/hf");
    let c = HubConfig::from_env();
    assert_eq!(c.cache_dir, home.join("hf/hub"));
    assert_eq!(c.token_path, home.join("hf/token"));

    std::env::set_var("HF_HUB_CACHE", tmp.path().join("c"));
    std::env::set_var("HF_TOKEN_PATH", home.join(".cache/huggingface/token"));
    std::env::set_var("HF_ENDPOINT", "http://127.0.0.1:5/");
    std::env::set_var("HF_HUB_OFFLINE", "yes");
    let c = HubConfig::from_env();
    assert_eq!(c.cache_dir, tmp.path().join("c"));
    assert_eq!(c.token.as_deref(), Some("hf_file"));
    assert_eq!(c.endpoint, "http://127.0.0.1:5");
    assert!(c.offline);

    std::env::set_var("HF_TOKEN", "hf_env");
    std::env::set_var("HF_HUB_OFFLINE", "0");
    let c = HubConfig::from_env();
    assert_eq!(c.token.as_deref(), Some("hf_env"));
    assert!(!c.offline);
    std::env::set_var("TRANSFORMERS_OFFLINE", "1");
    assert!(HubConfig::from_env().offline);
    clear();
}
