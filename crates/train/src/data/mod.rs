//! Training scenes: generated procedurally, rendered by POV-Ray, or read from `.torch` chunks.

pub mod procedural;
