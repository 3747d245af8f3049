//! `capsule-slam calibrate-light`: fit `light.toml` (gain, ambient, γ, vignetting) to frames of
//! a target of known albedo whose geometry the input's depth gives (a plane at a few known
//! distances is enough; the phantom with `--texture none` works too), see
//! `capsule_slam_calib::light_fit`.

use std::path::PathBuf;

use anyhow::{Context as _, anyhow, bail};
use capsule_slam_calib::light_fit::{FitOptions, LightSample, fit_light};
use capsule_slam_framework::config::InputConfig;
use capsule_slam_framework::files::{read_light_file, write_light_file};
use capsule_slam_io::Dataset;
use capsule_slam_plugins::common::maps::{normal_map, vertex_map};
use nalgebra::{Point3, Vector3};

/// Arguments of `calibrate-light`.
#[derive(clap::Args, Debug)]
pub struct CalibrateLightArgs {
    /// Input folder with depth (TUM layout and camera.toml) of the calibration target.
    #[arg(long)]
    input: PathBuf,
    /// The target's linear albedo: one value (grey) or R,G,B (the phantom's mucosa with
    /// `--texture none`: 0.8,0.3,0.25).
    #[arg(long, value_delimiter = ',', default_value = "0.8,0.3,0.25")]
    albedo: Vec<f64>,
    /// LED profile exponent, given (with the light at the optical centre the fit cannot tell it
    /// from vignetting; the vignetting absorbs what this misses).
    #[arg(long, default_value_t = 1.0)]
    spot_exponent: f64,
    /// Light position in the camera frame, metres: x,y,z.
    #[arg(long, value_delimiter = ',', default_value = "0,0,0")]
    light_position_m: Vec<f64>,
    /// Use every N-th frame.
    #[arg(long, default_value_t = 30)]
    every: usize,
    /// Use every N-th pixel in x and y.
    #[arg(long, default_value_t = 4)]
    stride: usize,
    /// Where to write the fitted model.
    #[arg(long, default_value = "light.toml")]
    out: PathBuf,
}

pub fn run(args: &CalibrateLightArgs) -> anyhow::Result<()> {
    let albedo: [f64; 3] = match args.albedo.as_slice() {
        [g] => [*g; 3],
        [r, g, b] => [*r, *g, *b],
        _ => bail!("--albedo: give one value or three (R,G,B), not {}", args.albedo.len()),
    };
    if !albedo.iter().all(|a| a.is_finite() && *a > 0.0 && *a <= 1.0) {
        bail!("--albedo {albedo:?}: each value must be in (0, 1]");
    }
    let [x, y, z] = args.light_position_m.as_slice() else { bail!("--light-position-m: give x,y,z in metres") };
    let dataset = Dataset::open(&args.input, &InputConfig::default(), None).with_context(|| format!("opening {}", args.input.display()))?;
    if !dataset.has_depth() {
        bail!("{} has no depth.txt: calibrate-light needs the target's geometry as depth", args.input.display());
    }
    let rig = dataset.rig();
    let cam = rig.camera();
    let mut samples = Vec::new();
    for i in (0..dataset.len()).step_by(args.every.max(1)) {
        let frame = dataset.load(i)?;
        let depth = frame.depth_m.as_ref().ok_or_else(|| anyhow!("frame {i} has no depth"))?;
        let vertices = vertex_map(depth, cam);
        let normals = normal_map(&vertices, 2, 0.002);
        let image = frame.views.reference();
        let ignore = frame.masks.union();
        for py in (0..cam.height).step_by(args.stride.max(1)) {
            for px in (0..cam.width).step_by(args.stride.max(1)) {
                let (p, n) = (vertices.pixel(px, py), normals.pixel(px, py));
                if p[2] <= 0.0 || n == [0.0; 3] || ignore.as_ref().is_some_and(|m| m.at(px, py)) || !cam.in_fov(px as f64, py as f64) {
                    continue;
                }
                let c = image.pixel(px, py);
                if c.iter().any(|v| *v < 5 || *v > 250) {
                    continue;
                }
                samples.push(LightSample {
                    u: px as f64,
                    v: py as f64,
                    p_cam: Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])),
                    n_cam: Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2])),
                    value: c.map(|v| f64::from(v) / 255.0),
                });
            }
        }
    }
    let opts = FitOptions { albedo, position_m: [*x, *y, *z], spot_exponent: args.spot_exponent, ..FitOptions::default() };
    let fit = fit_light(&samples, cam, &opts).with_context(|| format!("fitting the light to {}", args.input.display()))?;
    let l = &fit.light;
    println!("samples           {} kept of {}", fit.samples, samples.len());
    println!("rms residual      {:.4} (encoded, 0-1)", fit.rms);
    println!("gain              {:.4}", l.gain);
    println!("ambient           {:.4}", l.ambient);
    println!("gamma             {:.3}", l.gamma);
    println!("vignetting        {:?}", l.vignetting.iter().map(|v| (v * 1e4).round() / 1e4).collect::<Vec<_>>());
    let truth_path = args.input.join("light.toml");
    if truth_path.exists() && truth_path != args.out {
        let t = read_light_file(&truth_path)?;
        // V · spot at 95 % of the field-of-view radius, right of the centre.
        let edge_u = cam.cx + 0.95 * cam.fov_radius_px.unwrap_or(cam.cx);
        let edge = Point3::new((edge_u - cam.cx) / cam.fx, 0.0, 1.0);
        let axis = Point3::new(0.0, 0.0, edge.coords.norm());
        let corner = |m: &capsule_slam_framework::light::LightModel| m.vignetting_at(cam, edge_u, cam.cy) * m.falloff(&edge) / m.falloff(&axis);
        println!(
            "input light.toml  gain {:.4}, ambient {:.4}, gamma {:.3}, V·spot at the field-of-view edge {:.4} (fitted {:.4})",
            t.gain,
            t.ambient,
            t.gamma,
            corner(&t),
            corner(l)
        );
    }
    write_light_file(&args.out, l).with_context(|| format!("writing {}", args.out.display()))?;
    println!("written to        {}", args.out.display());
    Ok(())
}
