//! Camera images in the agent loop: when a camera event carries an image
//! (rendered simulation, real data), the image frontend makes its feature
//! frame, and the image with its tracks goes to the MCAP log. Built without the
//! `vision` feature, an agent refuses image input with a clear error.

use crate::agent_log::AgentLog;
use crate::frontend::FrontendOptions;
use common::camera::CameraModel;
use simulator::camera_sim::CameraEvent;

/// The frontend of an agent whose camera gives images.
#[derive(Debug)]
pub struct ImageFrames {
    #[cfg(feature = "vision")]
    frontend: crate::frontend::Frontend,
    /// Log every this many images (the image and its tracks).
    log_every: u64,
    frames: u64,
}

impl ImageFrames {
    /// A frontend for images of `camera`; an error when the agent was built
    /// without the `vision` feature.
    pub fn new(
        opts: &FrontendOptions,
        camera: CameraModel,
        log_every: u64,
    ) -> Result<Self, String> {
        #[cfg(feature = "vision")]
        {
            let frontend =
                crate::frontend::Frontend::new(opts.clone(), camera).map_err(|e| e.to_string())?;
            Ok(Self {
                frontend,
                log_every: log_every.max(1),
                frames: 0,
            })
        }
        #[cfg(not(feature = "vision"))]
        {
            let _ = (opts, camera, log_every);
            Err(
                "the camera gives images, but this agent was built without the image \
                 frontend: build with `--features agent/vision`"
                    .into(),
            )
        }
    }

    /// Replaces the event's frame with the frontend's features of its image
    /// (events without an image are left alone) and logs the image with its
    /// tracks every `log_every` images.
    pub fn apply(&mut self, c: &mut CameraEvent, log: Option<&mut AgentLog>) -> Result<(), String> {
        let Some(image) = c.image.clone() else {
            return Ok(());
        };
        #[cfg(feature = "vision")]
        {
            let out = self
                .frontend
                .process(c.frame.t, &image)
                .map_err(|e| e.to_string())?;
            if let Some(log) = log.filter(|_| self.frames % self.log_every == 0) {
                let _ = log.image(c.frame.t, &image);
                let _ = log.tracks(&out.frame, &out.new_ids);
            }
            self.frames += 1;
            c.frame = out.frame;
            Ok(())
        }
        #[cfg(not(feature = "vision"))]
        {
            let _ = (image, log, self.frames, self.log_every);
            Err("built without the vision feature".into())
        }
    }
}
