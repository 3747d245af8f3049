//! The stages before tracking (preprocessors and depth) as [`super::Pipeline`] runs them, and
//! a frame handed in ahead ([`super::Pipeline::push`]): prepared beside the fusion of the frame
//! before it as far as no stage reads the prediction, the rest in its turn.

use std::time::Instant;

use crate::camera::Rig;
use crate::context::Context;
use crate::depth_error::depth_error;
use crate::error::{PipelineError, StageError};
use crate::frame::{CameraFrame, DepthSource, RgbdFrame, Views};
use crate::map::ModelView;
use crate::stage::{DepthEstimator, Preprocessor, Tracker};

use super::record::{FrameRecord, ms_since, report, stage_err};

/// A frame handed in with [`Pipeline::push`] and not processed yet.
pub(super) enum Pending {
    /// As it came: it is prepared in its turn.
    Raw(Box<CameraFrame>),
    /// Prepared beside the fusion of the frame before it.
    Prepared(Box<Prepared>),
}

impl Pending {
    pub(super) fn index(&self) -> usize {
        match self {
            Pending::Raw(f) => f.index,
            Pending::Prepared(p) => p.rec.index,
        }
    }
}

/// A frame after steps 1–2 or 1–3 (or the error that stopped them, told in its turn), with its
/// record so far and, when kept, its input image.
pub(super) struct Prepared {
    pub(super) frame: Result<Ahead, PipelineError>,
    pub(super) rec: FrameRecord,
    pub(super) input: Option<crate::image::Rgb8>,
}

/// How far a frame was prepared.
pub(super) enum Ahead {
    /// Preprocessed (the depth estimator reads the prediction, so its depth waits).
    Preprocessed(CameraFrame),
    /// Preprocessed, its depth estimated and the tracker's preparation done.
    Rgbd(RgbdFrame),
}

/// The stages before tracking, borrowed from the pipeline.
pub(super) struct Front<'p> {
    pub(super) preprocessors: &'p mut Vec<(String, Box<dyn Preprocessor>)>,
    pub(super) depth: &'p mut (String, Box<dyn DepthEstimator>),
    pub(super) rig: &'p Rig,
    pub(super) keep_last: bool,
}

impl Front<'_> {
    /// Steps 1–2 of `frame`, with the map's `prediction` (at the last trusted pose) when there
    /// is one, and its input image when it is kept.
    pub(super) fn preprocess_kept(&mut self, mut frame: CameraFrame, prediction: Option<&ModelView>) -> Prepared {
        let mut rec = FrameRecord::new(frame.index, frame.timestamp_s);
        let input = self.keep_last.then(|| frame.views.reference().clone());
        let frame = match (self.rig, &frame.views) {
            (Rig::Stereo { .. }, Views::Mono(_)) => {
                Err(stage_err(frame.index, "input", StageError::invalid_input("the rig is stereo but the frame has one view")))
            }
            _ => self.preprocess(&mut frame, &mut rec, prediction).map(|()| Ahead::Preprocessed(frame)),
        };
        Prepared { frame, rec, input }
    }

    /// [`Front::preprocess_kept`] without a prediction (no preprocessor reads it) and, given the
    /// `tracker` (the depth estimator does not read it either), step 3 and the tracker's
    /// [`Tracker::prepare`], timed with its tracking.
    pub(super) fn prepare_ahead(&mut self, frame: CameraFrame, tracker: Option<&mut (String, Box<dyn Tracker>)>) -> Prepared {
        let mut prepared = self.preprocess_kept(frame, None);
        let Some((tname, tracker)) = tracker else { return prepared };
        prepared.frame = match prepared.frame {
            Ok(Ahead::Preprocessed(frame)) => self.estimate_depth(frame, &mut prepared.rec, None).map(|rgbd| {
                let t = Instant::now();
                tracker.prepare(&rgbd, &mut Context::new(rgbd.index, self.rig, None, report(&mut prepared.rec, tname)));
                prepared.rec.ms.track = ms_since(t);
                Ahead::Rgbd(rgbd)
            }),
            other => other,
        };
        prepared
    }

    /// Steps 1–2: the preprocessors, in order, on the frame in place.
    fn preprocess(&mut self, frame: &mut CameraFrame, rec: &mut FrameRecord, prediction: Option<&ModelView>) -> Result<(), PipelineError> {
        let t = Instant::now();
        let idx = frame.index;
        for (name, p) in self.preprocessors.iter_mut() {
            p.process(frame, &mut Context::new(idx, self.rig, prediction, report(rec, name))).map_err(|e| stage_err(idx, name, e))?;
        }
        rec.ms.preprocess = ms_since(t);
        Ok(())
    }

    /// Step 3: depth of the reference view, scored against the input's depth when it was
    /// estimated; the frame becomes what the later stages see.
    pub(super) fn estimate_depth(&mut self, frame: CameraFrame, rec: &mut FrameRecord, prediction: Option<&ModelView>) -> Result<RgbdFrame, PipelineError> {
        let t = Instant::now();
        let idx = frame.index;
        let (dname, depth) = &mut *self.depth;
        let est = depth.estimate(&frame, &mut Context::new(idx, self.rig, prediction, report(rec, dname))).map_err(|e| stage_err(idx, dname, e))?;
        rec.ms.depth = ms_since(t);
        if depth.source() == DepthSource::Estimated {
            rec.depth_abs_rel = frame.depth_m.as_ref().and_then(|truth| depth_error(&est.depth_m, truth, false)).map(|e| e.abs_rel);
        }
        let colour = match frame.views {
            Views::Mono(c) => c,
            Views::Stereo { left, .. } => left,
        };
        Ok(RgbdFrame {
            depth_source: depth.source(),
            index: idx,
            timestamp_s: frame.timestamp_s,
            colour,
            depth_m: est.depth_m,
            depth_confidence: est.confidence,
            depth_sigma_m: est.sigma_m,
            depth_sigma_correlation_px: est.sigma_correlation_px,
            photometry: frame.photometry,
            albedo: est.albedo,
            gt_t_world_cam: frame.gt_t_world_cam,
            masks: frame.masks,
            sample_share: frame.sample_share,
            derived: Default::default(),
        })
    }
}
