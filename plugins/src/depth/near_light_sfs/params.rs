//! The parameters of `near-light-sfs`: the photometric model's albedo and light file, the
//! grid solve and the valid ranges.

use serde::{Deserialize, Serialize};

capsule_slam_framework::plugin_params! {
    /// Parameters of `near-light-sfs`.
    pub struct NearLightSfsParams {
        /// Luminance albedo ρ of the tissue (NTSC-weighted linear reflectance; default: the
        /// built-in phantom's mucosa).
        pub albedo: f64 = 0.444; unit = "-"; range = 0.001..=1.0;
        /// Where each pixel's albedo comes from: `constant` (`albedo`), or `map` (the map's
        /// fused albedo seen in the prediction at the last pose, `albedo` where it has none).
        pub albedo_source: AlbedoSource = AlbedoSource::Constant; unit = "-";
        /// The light model, relative to the input folder (written by the phantom or by
        /// `capsule-slam calibrate-light`).
        pub light_file: String = "light.toml".to_string(); unit = "path";
        /// Cell size of the Gauss-Newton grid (8 px: 40×40 cells at 320×320; 4 px resolves
        /// finer folds but averages less of the albedo texture away and costs 4× more).
        pub cell_px: u32 = 8; unit = "px"; range = 1.0..=64.0;
        /// Grid levels, each half the cell size of the one before (coarse to fine); the finest
        /// has `cell_px`. 2 tracks as well as 1 at about 30 % less time
        /// (`docs/results/depth.md`).
        pub levels: u32 = 2; unit = "-"; range = 1.0..=4.0;
        /// Most Gauss-Newton iterations on the coarsest grid (0 = pure fall-off).
        pub iterations: u32 = 10; unit = "-"; range = 0.0..=100.0;
        /// Most Gauss-Newton iterations on each finer grid.
        pub fine_iterations: u32 = 3; unit = "-"; range = 0.0..=100.0;
        /// Start from the previous frame's solution where it fits this frame better than the
        /// fall-off start does. Off by default so that a frame's depth does not depend on the
        /// frames before it (on: about 20 % faster, `docs/results/depth.md`).
        pub warm_start: bool = false; unit = "-";
        /// Stop when an iteration lowers the cost by less than this fraction.
        pub tolerance: f64 = 0.01; unit = "-"; range = 0.0..=1.0;
        /// A Levenberg-Marquardt step that does not lower the cost is tried at half and a
        /// quarter of its length before the damping grows (a new sparse factorisation each
        /// time): the damping grows by 10× from about 10⁻⁴ of the diagonal, so the first
        /// retries give nearly the same overshooting step. On: about 18 % fewer
        /// factorisations, lower ATE on all seven rigid presets and on walls moving by 2 mm, but
        /// two more of six runs lose track on presets 4 and 5 with a 4 mm wave; off by default
        /// so that the measured figures stay as they are (`docs/results/depth.md`, "Speed of
        /// `near-light-sfs`").
        pub line_search: bool = false; unit = "-";
        /// Weight λ of the curvature prior on the log depth, per radian² of view angle: each
        /// cell's second difference of ln z is weighted by λ / h², h = cell_px / fx the cell's
        /// angle, so the prior means the same at any resolution (default: the lowest textured
        /// single-frame error on the phantom, `docs/results/depth.md`).
        pub smoothness: f64 = 0.025; unit = "rad²"; range = 0.0..=1000.0;
        /// cos θ below which the incidence term is softly clamped (grazing incidence is
        /// ill-conditioned).
        pub min_cos: f64 = 0.1; unit = "-"; range = 0.001..=1.0;
        /// `shading`: add each pixel's brightness deviation from the grid's model (fine shape,
        /// and albedo texture read as shape); `smooth`: the interpolated grid depth only.
        /// Default `smooth`: on textured tissue the per-pixel term reads albedo as shape.
        pub detail: Detail = Detail::Smooth; unit = "-";
        /// Pixels with any 8-bit channel at or above this are saturated (highlights): no depth.
        pub saturation: u8 = 250; unit = "8-bit"; range = 1.0..=255.0;
        /// Pixels darker than this linear luminance get no depth (noise dominates).
        pub min_luminance: f64 = 0.003; unit = "-"; range = 0.0..=1.0;
        /// Valid depth range: nearest.
        pub min_depth_m: f32 = 0.002; unit = "m"; range = 0.0..=100.0;
        /// Valid depth range: farthest.
        pub max_depth_m: f32 = 0.25; unit = "m"; range = 0.0..=100.0;
    }
}

/// Where a pixel's albedo comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlbedoSource {
    /// The parameter `albedo` everywhere.
    Constant,
    /// The map's albedo where the prediction has one.
    Map,
}

/// What the per-pixel depth keeps of the image beyond the grid solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Detail {
    /// Grid depth plus each pixel's brightness deviation.
    Shading,
    /// Grid depth only (bilinear).
    Smooth,
}
