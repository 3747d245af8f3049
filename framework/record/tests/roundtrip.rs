//! A recording read back: every entity logged as often as the options say, and bad paths named.

use capsule_slam_framework::camera::PinholeCamera;
use capsule_slam_framework::geometry::{Iso3, StampedPose};
use capsule_slam_framework::image::Rgb8;
use capsule_slam_framework::map::{ModelView, Surfel, SurfelSet};
use capsule_slam_framework::pipeline::FrameRecord;
use capsule_slam_record::{RecordError, RecordOptions, Recorder, Step, contents};
use nalgebra::{Point3, Vector3};

fn surfels(n: usize) -> SurfelSet {
    SurfelSet::new(
        (0..n)
            .map(|i| Surfel {
                position_m: Point3::new(i as f32 * 1e-4, 0.0, 0.05),
                normal: Vector3::new(0.0, 0.0, -1.0),
                colour: [200, 100, 50],
                confidence: 1.0,
                radius_m: 2e-4,
                t0: 0,
                t: 0,
                albedo: 0.0,
                sigma_m: 0.0,
                warp_m: Vector3::zeros(),
            })
            .collect(),
    )
}

#[test]
fn every_entity_is_logged_as_often_as_asked_and_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.rrd");
    let cam = PinholeCamera::new(16, 12, 20.0, 20.0, 7.5, 5.5);
    let mut rec = Recorder::create(&path, RecordOptions { map_every: 4, max_map_points: 50 }).unwrap();
    let truth: Vec<StampedPose> = (0..10).map(|i| StampedPose { timestamp_s: i as f64, t_world_cam: Iso3::translation(i as f64 * 1e-3, 0.0, 0.0) }).collect();
    rec.log_ground_truth(&truth).unwrap();
    let input = Rgb8::filled(16, 12, 90);
    let mut maps_asked = 0;
    for i in 0..10 {
        let mut r = FrameRecord::new(i, i as f64);
        r.t_world_cam = truth[i].t_world_cam;
        // Frames 0–5 have a prediction at their pose; 6–9 one from an older pose (a lost frame).
        let at = if i < 6 { r.t_world_cam } else { Iso3::identity() };
        let prediction = ModelView::empty(16, 12, at);
        let step = Step { record: &r, camera: &cam, input: Some(&input), frame: None, prediction: Some(&prediction), trajectory: &truth[..=i] };
        rec.log_step(&step, || {
            maps_asked += 1;
            Some(surfels(120))
        })
        .unwrap();
    }
    assert_eq!(maps_asked, 3, "frames 0, 4 and 8 only");
    let written = rec.finish(9, &truth, Some(&surfels(120))).unwrap();
    assert_eq!(written, path);

    let c = contents(&path).unwrap();
    let rows = |e: &str| c.rows_of(e);
    assert_eq!(rows("world/camera"), 10);
    assert_eq!(rows("world/camera/image"), 1, "the pinhole, once");
    assert_eq!(rows("world/camera/image/input"), 10);
    assert_eq!(rows("world/camera/image/predicted_depth"), 6, "only predictions made at the frame's pose");
    assert_eq!(rows("world/camera/image/predicted_colour"), 6);
    assert_eq!(rows("world/camera/image/depth"), 0, "no frame was kept");
    assert_eq!(rows("world/map"), 4, "frames 0, 4, 8 and the end");
    assert_eq!(rows("world/trajectory/estimated"), 11, "every frame and the end");
    assert_eq!(rows("world/trajectory/ground_truth"), 1);
    assert_eq!(rows("metrics/ms_per_frame"), 10);
    assert_eq!(rows("metrics/warp_mean_mm"), 0, "no warp was reported");
}

#[test]
fn a_recording_that_cannot_be_created_or_read_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no/such/folder/run.rrd");
    match Recorder::create(&missing, RecordOptions::default()) {
        Err(e @ RecordError::Create { .. }) => assert!(e.to_string().contains("no/such/folder/run.rrd") && e.to_string().contains("writable"), "{e}"),
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("created a recording in a missing folder"),
    }
    let garbage = dir.path().join("garbage.rrd");
    std::fs::write(&garbage, b"this is not a recording").unwrap();
    let e = contents(&garbage).unwrap_err();
    assert!(matches!(e, RecordError::Read { .. }) && e.to_string().contains("garbage.rrd"), "{e}");
    let e = contents(&dir.path().join("absent.rrd")).unwrap_err();
    assert!(e.to_string().contains("absent.rrd"), "{e}");
}
