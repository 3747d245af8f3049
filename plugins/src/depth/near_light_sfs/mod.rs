//! `near-light-sfs`: shape from shading for a capsule's near light (after
//! Okatani & Deguchi 1997, CVIU 66(2), and Prados & Faugeras 2005): a perspective camera, a
//! point light at (or beside) the optical centre, and the calibrated photometric model of
//! `light.toml`,
//!
//! `L(u) = V(u) · ρ · (gain · cos θ · (ref / r)² · spot + ambient)`,
//!
//! with L the linear NTSC luminance of the pixel (each channel gamma-decoded), ρ the tissue's
//! luminance albedo, r the distance from the light. Per frame:
//! 1. every usable pixel (not masked by the frame's specular or out-of-view masks, not
//!    saturated, not too dark) gives `ln E = ln(L / (V ρ) − ambient)`;
//! 2. the pure fall-off estimate (cos θ = 1: bright = near) starts a Gauss-Newton solve of the
//!    irradiance equation for the log depth on a grid of `cell_px` cells with a curvature prior
//!    ([`solve`]);
//! 3. each pixel's depth is the interpolated grid depth, plus (`detail = "shading"`) the
//!    per-pixel brightness deviation from the grid's modelled irradiance, `½ (ln M − ln E)`.
//!
//! The output is metric: its scale comes from the light model and the assumed albedo.
//!
//! Beside the depth it returns each pixel's observed albedo, `ρ_obs = (L / V) / (M + ambient)`
//! with M the grid's modelled irradiance (the light model on the smooth solved surface), for
//! the fuser to average into the map. With `albedo_source = "map"` the albedo of each pixel is
//! the map's (the prediction's albedo at the last pose, `ctx.prediction`) where the map has
//! one, and `albedo` elsewhere. A map whose geometry came from this same estimator gives back,
//! at the scale of the grid, the albedo it assumed (the solved surface explains each cell's
//! brightness with it): what the map adds then is the texture finer than a cell. A map with
//! albedo-independent geometry (measured or stereo depth) gives the true albedo.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::frame::DividedFalloff;
use capsule_slam_framework::light::LightModel;
use capsule_slam_framework::light::vignetting::cos_alpha;
use capsule_slam_framework::registry::BuildEnv;
use capsule_slam_framework::{CameraFrame, Context, DepthEstimate, DepthEstimator, DepthMap, GrayF32, Mask, Plugin, Rgb8, StageError, register};

pub use params::{AlbedoSource, Detail, NearLightSfsParams};
use pixels::{Pixel, PixelInput, Solved};
use solve::{Bilinear, CellData, Grid, Photometry, SolveSettings, cost, solve};

/// One frame's result.
#[derive(Debug, Clone, PartialEq)]
pub struct SfsOutput {
    /// Depth along z, metres; 0 = none.
    pub depth_m: DepthMap,
    /// Confidence in [0, 1].
    pub confidence: GrayF32,
    /// Observed albedo per pixel (linear luminance; 0 where there is no depth).
    pub albedo: GrayF32,
    /// Pixels whose albedo came from the map.
    pub map_albedo_pixels: usize,
}

impl SfsOutput {
    fn empty(w: usize, h: usize) -> Self {
        Self { depth_m: DepthMap::new(w, h), confidence: GrayF32::new(w, h), albedo: GrayF32::new(w, h), map_albedo_pixels: 0 }
    }
}

/// The near-light perspective shape-from-shading estimator.
pub struct NearLightSfs {
    params: NearLightSfsParams,
    light: LightModel,
    /// Per-camera tables, built on the first frame.
    tables: Option<Tables>,
    /// Gamma decoding of 8-bit values.
    decode: [f64; 256],
    /// The last frame's coarsest log-depth grid (warm start).
    previous: Option<Vec<f64>>,
    /// Step 1's per-pixel buffer, kept from frame to frame.
    irradiance: Vec<Option<Pixel>>,
    /// Sparse factorisations of the last frame's solve.
    factorisations: usize,
    /// Whether the light came from a calibration (else the depth's scale is unknown).
    calibrated: bool,
    /// A warning of the build, told on the first frame.
    pending_warning: Option<String>,
}

/// What depends only on the camera.
struct Tables {
    camera: PinholeCamera,
    /// The solve's grids, coarsest first.
    levels: Vec<Grid>,
    /// The finest grid's bilinear taps per pixel.
    fine_taps: Vec<Bilinear>,
    /// `1 / V(u)` per pixel; `None` outside the field of view.
    inv_vignetting: Vec<Option<f64>>,
    /// Per pixel `cos α` (the ray's angle to the axis) and `cos^s α`, the LED profile with the
    /// light's spot exponent s, for images whose fall-off a preprocessor divided out.
    cos_alpha: Vec<[f64; 2]>,
}

impl Plugin for NearLightSfs {
    const NAME: &'static str = "near-light-sfs";
    const SUMMARY: &'static str = "metric depth from one image under the capsule's near light (albedo cos θ / r², calibrated light.toml): Gauss-Newton on a log-depth grid from the fall-off start";
    type Params = NearLightSfsParams;

    /// The light of `light_file`; without that file, [`LightModel::uncalibrated`] (a depth of
    /// unknown scale, warned on the first frame). A file that exists but cannot be read is an
    /// error: it was meant to be used.
    fn build(params: NearLightSfsParams, env: &BuildEnv) -> Result<Self, StageError> {
        let path = env.input_file(&params.light_file);
        if !path.exists() {
            let mut s = Self::with_light(params, LightModel::uncalibrated());
            s.calibrated = false;
            s.pending_warning = Some(format!(
                "no {}: the light is assumed ({}), so the depth, the map and the trajectory have an unknown scale (figures are Sim(3)-aligned); `capsule-slam calibrate-light` fits the capsule's light.toml",
                path.display(),
                s.light.describe()
            ));
            return Ok(s);
        }
        let light = capsule_slam_framework::files::read_light_file(&path).map_err(|e| {
            StageError::invalid_input(format!("{e}; `near-light-sfs` reads the capsule's light model there: fix the file (`capsule-slam calibrate-light` fits one), or remove it to run with an assumed light and an unknown scale; for an RGB-D input use the measured depth: --set pipeline.depth=sensor"))
        })?;
        Ok(Self::with_light(params, light))
    }
}

impl NearLightSfs {
    /// An estimator with a given light model.
    pub fn with_light(params: NearLightSfsParams, light: LightModel) -> Self {
        let decode = std::array::from_fn(|v| light.decode(v as f64 / 255.0));
        Self { params, light, tables: None, decode, previous: None, irradiance: Vec::new(), factorisations: 0, calibrated: true, pending_warning: None }
    }

    fn tables(&mut self, cam: &PinholeCamera) -> Result<&Tables, StageError> {
        if self.tables.as_ref().is_none_or(|t| t.camera != *cam) {
            let (w, h) = (cam.width, cam.height);
            let inv_vignetting = (0..w * h)
                .map(|k| {
                    let (x, y) = ((k % w) as f64, (k / w) as f64);
                    let v = self.light.vignetting_at(cam, x, y);
                    (cam.in_fov(x, y) && v > 0.0).then(|| 1.0 / v)
                })
                .collect();
            let levels: Vec<Grid> = (0..self.params.levels).rev().map(|l| Grid::new(cam, (self.params.cell_px as usize) << l)).collect::<Result<_, _>>()?;
            let fine_taps = match levels.last() {
                Some(g) => (0..w * h).map(|k| g.bilinear((k % w) as f64, (k / w) as f64)).collect(),
                None => vec![Bilinear::default(); w * h],
            };
            let spot = self.light.spot_exponent;
            let cos_alpha = (0..w * h)
                .map(|k| {
                    let c = cos_alpha(cam, (k % w) as f64, (k / w) as f64);
                    [c, c.powf(spot)]
                })
                .collect();
            self.tables = Some(Tables { camera: cam.clone(), levels, fine_taps, inv_vignetting, cos_alpha });
        }
        self.tables.as_ref().ok_or_else(|| StageError::invalid_input("near-light-sfs: no camera tables".to_string()))
    }

    /// Metric depth, confidence and observed albedo from the image; `map_albedo` (the map's
    /// prediction at the last pose, used with `albedo_source = "map"`) gives a pixel's albedo
    /// where it is positive.
    ///
    /// `divided` says which fall-off a preprocessor already divided out of the image (the
    /// frame's `photometry`): then the model's V and LED profile are replaced by the
    /// preprocessor's scale (and, for a divided flat field, cos³α is multiplied back in, as the
    /// cos θ / r² of the shape is this estimator's cue).
    pub fn depth(
        &mut self,
        image: &Rgb8,
        ignore: Option<&Mask>,
        cam: &PinholeCamera,
        map_albedo: Option<&GrayF32>,
        divided: Option<DividedFalloff>,
    ) -> Result<SfsOutput, StageError> {
        let p = self.params.clone();
        let decode = self.decode;
        let mut light = self.light.clone();
        let spot_exponent = light.spot_exponent;
        if divided.is_some() {
            light.spot_exponent = 0.0;
        }
        self.factorisations = 0;
        let previous = self.previous.take();
        let mut irradiance = std::mem::take(&mut self.irradiance);
        let tables = self.tables(cam)?;
        let (w, h) = image.size();
        let map_albedo = map_albedo.filter(|a| p.albedo_source == AlbedoSource::Map && a.size() == (w, h));
        // 1. Per usable pixel: L / V, E, the confidence of its signal level, its albedo's origin.
        let input = PixelInput { image, ignore, map_albedo, divided, decode: &decode, spot_exponent };
        pixels::irradiance(&input, &light, (&tables.inv_vignetting, &tables.cos_alpha), &p, &mut irradiance);
        let map_albedo_pixels = irradiance.iter().flatten().filter(|px| px.from_map).count();
        // 2. Coarse to fine on the grids.
        let Some(solved) = solve_levels(&tables.levels, &irradiance, w, &light, &p, cam, previous)? else {
            return Ok(SfsOutput::empty(w, h));
        };
        // 3. Per pixel: bilinear over the cell centres that exist.
        let mut out = SfsOutput { map_albedo_pixels, ..SfsOutput::empty(w, h) };
        pixels::per_pixel(&irradiance, &tables.fine_taps, &solved, &p, [out.depth_m.data_mut(), out.confidence.data_mut(), out.albedo.data_mut()]);
        self.irradiance = irradiance;
        self.previous = Some(solved.coarsest);
        self.factorisations = solved.factorisations;
        Ok(out)
    }
}

/// Per cell of `grid`: the log of the mean irradiance of its pixels (the mean is robust to the
/// noise of dark pixels, whose logarithm is biased) and its share of usable pixels.
fn cell_data(grid: &Grid, irradiance: &[Option<Pixel>], w: usize) -> Vec<CellData> {
    let mut sum = vec![(0.0, 0usize); grid.cells.len()];
    // Row by row, with each column's grid column looked up (no division per pixel); the pixels
    // are summed in the same order as before.
    let grid_col: Vec<usize> = (0..w).map(|x| x / grid.cell_px).collect();
    for (y, row) in irradiance.chunks(w.max(1)).enumerate() {
        let cells = &grid.index[(y / grid.cell_px) * grid.cols..];
        for (v, &gc) in row.iter().zip(&grid_col) {
            if let (Some(px), Some(c)) = (v, cells[gc]) {
                sum[c].0 += px.e;
                sum[c].1 += 1;
            }
        }
    }
    let area = (grid.cell_px * grid.cell_px) as f64;
    sum.iter().map(|(s, m)| if *m > 0 { CellData { ln_e: (s / *m as f64).ln(), weight: *m as f64 / area } } else { CellData::default() }).collect()
}

/// The coarsest grid's start: the pure fall-off (cos θ = 1, light at the optical centre, spot
/// along the ray), or the previous frame's solution where it explains this frame better (with
/// `warm_start`); `None` when no cell has data.
fn coarse_start(grid: &Grid, data: &[CellData], light: &LightModel, photometry: &Photometry, smoothness: f64, warm: Option<Vec<f64>>) -> Option<Vec<f64>> {
    let ln_gain = (light.gain * light.ref_distance_m * light.ref_distance_m).ln();
    let start: Vec<Option<f64>> = grid
        .cells
        .iter()
        .zip(data)
        .map(|(cell, d)| {
            let norm = cell.ray.norm();
            (d.weight > 0.0).then(|| 0.5 * (ln_gain + light.spot_exponent * (1.0 / norm).ln() - d.ln_e) - norm.ln())
        })
        .collect();
    let known: Vec<f64> = start.iter().flatten().copied().collect();
    if known.is_empty() {
        return None;
    }
    let mean = known.iter().sum::<f64>() / known.len() as f64;
    let falloff: Vec<f64> = start.iter().map(|z| z.unwrap_or(mean)).collect();
    Some(match warm {
        Some(prev) if prev.len() == falloff.len() && cost(grid, photometry, data, &prev, smoothness) < cost(grid, photometry, data, &falloff, smoothness) => {
            prev
        }
        _ => falloff,
    })
}

/// The last solved pyramid level: its grid, its cells' ζ (log depth), their data and the solve's residual.
type SolvedLevel<'g> = (&'g Grid, Vec<f64>, Vec<CellData>, Vec<f64>);

/// Gauss-Newton on each grid, coarsest first, each finer grid started from the coarser
/// solution; `None` when no cell has data.
fn solve_levels(
    levels: &[Grid],
    irradiance: &[Option<Pixel>],
    w: usize,
    light: &LightModel,
    p: &NearLightSfsParams,
    cam: &PinholeCamera,
    previous: Option<Vec<f64>>,
) -> Result<Option<Solved>, StageError> {
    let photometry = Photometry::new(light, p.min_cos);
    let smoothness = |grid: &Grid| p.smoothness * (cam.fx / grid.cell_px as f64).powi(2);
    let mut warm = previous.filter(|_| p.warm_start);
    let (mut factorisations, mut coarsest) = (0, None);
    let mut solved: Option<SolvedLevel<'_>> = None;
    for grid in levels {
        let data = cell_data(grid, irradiance, w);
        let mut zeta: Vec<f64> = match &solved {
            None => match coarse_start(grid, &data, light, &photometry, smoothness(grid), warm.take()) {
                Some(z) => z,
                None => return Ok(None),
            },
            Some((coarse, z, _, _)) => grid
                .cells
                .iter()
                .map(|cell| {
                    let (u, v) = grid.centre_px(cell);
                    coarse.interpolate(u, v, |c| z[c]).unwrap_or(0.0)
                })
                .collect(),
        };
        let iterations = if solved.is_none() { p.iterations } else { p.iterations.min(p.fine_iterations) };
        let (residual, n_factor) = solve(
            grid,
            &photometry,
            &data,
            &mut zeta,
            &SolveSettings { iterations, smoothness: smoothness(grid), tolerance: p.tolerance, line_search: p.line_search },
        )?;
        if solved.is_none() {
            coarsest = Some(zeta.clone());
        }
        factorisations += n_factor;
        solved = Some((grid, zeta, data, residual));
    }
    let (Some((_, zeta, data, residual)), Some(coarsest)) = (solved, coarsest) else { return Ok(None) };
    let ln_m: Vec<f64> = residual.iter().zip(&data).map(|(r, d)| r + d.ln_e).collect();
    let z_cell: Vec<f64> = zeta.iter().map(|z| z.exp()).collect();
    Ok(Some(Solved { data, ln_m, z_cell, coarsest, factorisations }))
}

impl DepthEstimator for NearLightSfs {
    /// With `albedo_source = "map"` only: the map's albedo in the prediction.
    fn reads_prediction(&self) -> bool {
        self.params.albedo_source == AlbedoSource::Map
    }

    fn metric_scale(&self) -> bool {
        self.calibrated
    }

    fn estimate(&mut self, frame: &CameraFrame, ctx: &mut Context) -> Result<DepthEstimate, StageError> {
        if let Some(w) = self.pending_warning.take() {
            ctx.warn(w);
        }
        let ignore = frame.masks.union();
        let divided = frame.photometry.divided;
        if let Some(d) = divided
            && (d.gamma - self.light.gamma).abs() > 1e-6
        {
            ctx.warn(format!(
                "frame {}: the vignetting correction linearised with gamma {} but the light model has {}: the depth is biased; give both the same gamma",
                frame.index, d.gamma, self.light.gamma
            ));
        }
        let out = self.depth(frame.views.reference(), ignore.as_ref(), ctx.rig.camera(), ctx.prediction.map(|v| &v.albedo), divided)?;
        let valid = out.depth_m.data().iter().filter(|d| **d > 0.0).count();
        ctx.count("valid_pixels", valid as f64);
        ctx.count("factorisations", self.factorisations as f64);
        if self.params.albedo_source == AlbedoSource::Map {
            ctx.count("map_albedo_share", out.map_albedo_pixels as f64 / valid.max(1) as f64);
        }
        if valid == 0 {
            ctx.warn("no pixel usable for shape from shading (all masked, saturated or too dark); the depth is empty");
        }
        Ok(DepthEstimate { depth_m: out.depth_m, confidence: Some(out.confidence), albedo: Some(out.albedo), sigma_m: None, sigma_correlation_px: 0.0 })
    }
}

register!(DepthEstimator, NearLightSfs);

mod params;
mod pixels;
mod solve;
#[cfg(test)]
mod tests;
