//! Colour-histogram matching.
