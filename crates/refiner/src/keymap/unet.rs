//! See keymap/mod.rs.
