//! The product's path from posed photos to novel views: preprocessing, context/target choice, model loading,
//! encoder → rasterizer → refiner → histogram matching, and the output writers.

pub mod video;
