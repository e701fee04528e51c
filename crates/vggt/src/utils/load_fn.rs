//! The official `load_and_preprocess_images` (being written).
