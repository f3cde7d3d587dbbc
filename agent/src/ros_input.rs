//! Live sensors over Zenoh: a robot's IMU and camera as ROS 2 topics
//! (`sensor_msgs/msg/Imu`, `sensor_msgs/msg/Image` in CDR), the way
//! `zenoh-bridge-ros2dds` (key = the topic without its leading `/`, e.g.
//! `cam0/image_raw`) and `rmw_zenoh` (key `<domain>/<topic>/<type>/<hash>`,
//! matched by `0/cam0/image_raw/**`) put them on the network.
//!
//! [`LiveSensors`] subscribes to both keys and turns the samples into the
//! simulator's events, in time order, for the same loop that runs a recorded
//! sequence. The samples come off the network: a payload that does not
//! decode is counted and logged, never fatal, and what waits for the loop is
//! bounded (images by count, IMU samples by a channel's capacity), so a
//! sensor that floods loses its newest samples, counted, instead of growing
//! the agent. [`publish_sequence`] is the other side: a EuRoC sequence
//! published as those topics, paced like the sensors that recorded it.

use crate::dataset::EurocDataset;
use crate::estimator::frame_output::BodyTwist;
use crate::transport::settings::ZenohSettings;
use common::image::GrayImage;
use common::measurement::{FeatureFrame, ImuSample};
use common::ros_cdr::{self, Header};
use common::trajectory::{StampedCovariance, StampedPose};
use nalgebra::{Matrix3, Vector3};
use simulator::camera_sim::{CameraEvent, TruthState};
use simulator::imu::Biases;
use simulator::SimEvent;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use thiserror::Error;
use zenoh::qos::CongestionControl;
use zenoh::{Session, Wait};

/// The Zenoh session of a live sensor link (both ends).
#[derive(clap::Args, Debug, Clone)]
pub struct ZenohArgs {
    /// A built-in Zenoh configuration (`loopback`, `lan`, `explicit-peers`,
    /// `tls`, `quic`) or the path of a json5 Zenoh configuration. A
    /// `zenoh-bridge-ros2dds` or a `rmw_zenoh` router on the robot is reached
    /// with `--connect tcp/<its address>:7447`.
    #[arg(long, default_value = "loopback")]
    pub zenoh_config: String,
    /// Endpoints to listen on (replace the configuration's).
    #[arg(long)]
    pub listen: Vec<String>,
    /// Endpoints to connect to (replace the configuration's).
    #[arg(long)]
    pub connect: Vec<String>,
    /// The IMU's key (`sensor_msgs/msg/Imu`): the topic without its leading
    /// `/` for `zenoh-bridge-ros2dds`, `<domain>/<topic>/**` for `rmw_zenoh`.
    #[arg(long, default_value = "imu0")]
    pub imu_key: String,
    /// The camera's key (`sensor_msgs/msg/Image`: mono8, mono16, rgb8, bgr8,
    /// rgba8 or bgra8).
    #[arg(long, default_value = "cam0/image_raw")]
    pub image_key: String,
}

impl ZenohArgs {
    /// The session's settings.
    pub fn settings(&self) -> ZenohSettings {
        ZenohSettings {
            config: self.zenoh_config.clone(),
            listen: self.listen.clone(),
            connect: self.connect.clone(),
            robot_certificates: None,
        }
    }

    /// The sensors' keys.
    pub fn keys(&self) -> SensorKeys {
        SensorKeys {
            imu: self.imu_key.clone(),
            image: self.image_key.clone(),
        }
    }
}

/// IMU samples (and decoded images) waiting for the estimator's loop.
const CHANNEL_CAPACITY: usize = 8192;
/// Decoded images waiting for the loop, at most: about a second of a camera.
const MAX_QUEUED_IMAGES: usize = 16;
/// Images held until the IMU reaches their time, at most: an IMU that stops
/// must not make the agent keep every image.
const MAX_HELD_IMAGES: usize = 32;
/// A gap between the camera's and the IMU's stamps beyond this, s, is
/// warned about: the two are not on one clock.
const CLOCK_GAP_S: f64 = 1.0;
/// Undecodable payloads logged one by one per topic; the rest are counted.
const BAD_LOGGED: u64 = 5;

/// Why live sensors could not be read or published.
#[derive(Debug, Error)]
pub enum LiveError {
    /// The Zenoh configuration or session failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// A setting is out of range.
    #[error("{0}")]
    Setting(String),
    /// The sequence to publish could not be read.
    #[error(transparent)]
    Dataset(#[from] crate::dataset::DatasetError),
}

fn zenoh_error(e: impl std::fmt::Display) -> LiveError {
    LiveError::Zenoh(e.to_string())
}

/// The Zenoh keys of the two sensors.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SensorKeys {
    /// `sensor_msgs/msg/Imu` samples.
    pub imu: String,
    /// `sensor_msgs/msg/Image` samples.
    pub image: String,
}

/// What arrived, per sensor: decoded, not decodable, dropped because the
/// loop was behind.
#[derive(Debug, Default)]
pub struct LiveCounts {
    /// IMU samples decoded.
    pub imu: AtomicU64,
    /// IMU payloads that did not decode.
    pub imu_bad: AtomicU64,
    /// IMU samples dropped (the loop was behind).
    pub imu_dropped: AtomicU64,
    /// Images decoded.
    pub images: AtomicU64,
    /// Image payloads that did not decode.
    pub images_bad: AtomicU64,
    /// Images dropped (the loop was behind, or the IMU never reached them).
    pub images_dropped: AtomicU64,
    /// The largest gap between an image's stamp and the newest IMU sample's
    /// when the image arrived, ms.
    pub clock_gap_ms: AtomicU64,
}

impl LiveCounts {
    /// One line for the log and the console.
    pub fn line(&self) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        format!(
            "IMU {} received, {} undecodable, {} dropped; images {} received, {} undecodable, {} dropped; \
             image stamps at most {} ms from the IMU's on arrival",
            g(&self.imu),
            g(&self.imu_bad),
            g(&self.imu_dropped),
            g(&self.images),
            g(&self.images_bad),
            g(&self.images_dropped),
            g(&self.clock_gap_ms)
        )
    }

    /// Nothing arrived that decoded.
    pub fn nothing_received(&self) -> bool {
        self.imu.load(Ordering::Relaxed) == 0 && self.images.load(Ordering::Relaxed) == 0
    }
}

enum Arrival {
    Imu(ImuSample),
    Image(f64, GrayImage),
}

/// When a live run ends.
#[derive(Clone, Debug)]
pub struct LiveLimits {
    /// Wait this long for the first sample.
    pub wait_first: Duration,
    /// After the first sample, end when nothing arrives for this long (the
    /// sensors stopped).
    pub idle: Duration,
    /// End after this long in any case (`None`: until stopped).
    pub max_duration: Option<Duration>,
}

/// Subscriptions to a robot's IMU and camera topics.
pub struct LiveSensors {
    session: Session,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    rx: Receiver<Arrival>,
    queued_images: Arc<AtomicUsize>,
    counts: Arc<LiveCounts>,
}

impl std::fmt::Debug for LiveSensors {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveSensors")
            .field("counts", &self.counts)
            .finish_non_exhaustive()
    }
}

impl LiveSensors {
    /// Opens a Zenoh session as `settings` say and subscribes to `keys`.
    pub fn open(settings: &ZenohSettings, keys: &SensorKeys) -> Result<Self, LiveError> {
        let config = crate::transport::zenoh::load_config(settings).map_err(zenoh_error)?;
        let session = zenoh::open(config).wait().map_err(zenoh_error)?;
        let (tx, rx) = std::sync::mpsc::sync_channel(CHANNEL_CAPACITY);
        let counts = Arc::new(LiveCounts::default());
        let queued_images = Arc::new(AtomicUsize::new(0));
        let imu = {
            let (tx, counts, key) = (tx.clone(), Arc::clone(&counts), keys.imu.clone());
            session
                .declare_subscriber(&keys.imu)
                .callback(move |sample| {
                    let bytes = sample.payload().to_bytes();
                    match ros_cdr::decode_imu(&bytes) {
                        Ok(m) => {
                            counts.imu.fetch_add(1, Ordering::Relaxed);
                            if let Err(TrySendError::Full(_)) =
                                tx.try_send(Arrival::Imu(m.sample()))
                            {
                                counts.imu_dropped.fetch_add(1, Ordering::Relaxed);
                            }
                        }
                        Err(e) => bad(&counts.imu_bad, &key, &e),
                    }
                })
                .wait()
                .map_err(zenoh_error)?
        };
        let image = {
            let (counts, key) = (Arc::clone(&counts), keys.image.clone());
            let queued = Arc::clone(&queued_images);
            session
                .declare_subscriber(&keys.image)
                .callback(move |sample| {
                    let bytes = sample.payload().to_bytes();
                    match ros_cdr::decode_image(&bytes) {
                        Ok(m) => {
                            counts.images.fetch_add(1, Ordering::Relaxed);
                            send_image(&tx, &queued, &counts, m.header.t_s(), m.image);
                        }
                        Err(e) => bad(&counts.images_bad, &key, &e),
                    }
                })
                .wait()
                .map_err(zenoh_error)?
        };
        Ok(Self {
            session,
            _subscribers: vec![imu, image],
            rx,
            queued_images,
            counts,
        })
    }

    /// A publisher of the estimated pose on `key`
    /// (`geometry_msgs/msg/PoseWithCovarianceStamped`, in the frame
    /// `frame_id`). It drops what a slow subscriber cannot take: the
    /// estimator never waits for the network.
    pub fn pose_publisher(&self, key: &str, frame_id: &str) -> Result<PosePublisher, LiveError> {
        self.publisher(key, frame_id, None)
    }

    /// A publisher of the estimate as `nav_msgs/msg/Odometry` on `key`: the
    /// pose in `frame_id`, the body's velocity and angular rate in
    /// `child_frame_id` (the IMU), each with its covariance. Drops as
    /// [`Self::pose_publisher`] does.
    pub fn odometry_publisher(
        &self,
        key: &str,
        frame_id: &str,
        child_frame_id: &str,
    ) -> Result<PosePublisher, LiveError> {
        self.publisher(key, frame_id, Some(child_frame_id.to_owned()))
    }

    fn publisher(
        &self,
        key: &str,
        frame_id: &str,
        child_frame_id: Option<String>,
    ) -> Result<PosePublisher, LiveError> {
        let publisher = self
            .session
            .declare_publisher(key.to_owned())
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(zenoh_error)?;
        Ok(PosePublisher {
            publisher,
            frame_id: frame_id.to_owned(),
            child_frame_id,
            sent: 0,
            failed: 0,
        })
    }

    /// What has arrived so far.
    pub fn counts(&self) -> Arc<LiveCounts> {
        Arc::clone(&self.counts)
    }

    /// The samples as the simulator's events: each image right after the
    /// last IMU sample at or before its time, as a recorded sequence gives
    /// them. Ends when `stop` is set or `limits` say so; the images still
    /// held then come last.
    pub fn events(self, stop: Arc<AtomicBool>, limits: LiveLimits) -> LiveEvents {
        LiveEvents {
            sensors: self,
            stop,
            limits,
            started: Instant::now(),
            arrivals: Arc::new(Mutex::new(VecDeque::new())),
            last_arrival: None,
            newest_imu_t: f64::NEG_INFINITY,
            held: VecDeque::new(),
            ready: VecDeque::new(),
            ended: false,
            clock_warned: false,
        }
    }
}

fn bad(counter: &AtomicU64, key: &str, e: &ros_cdr::CdrError) {
    let n = counter.fetch_add(1, Ordering::Relaxed);
    if n < BAD_LOGGED {
        tracing::warn!("{key}: payload dropped: {e}");
    } else if n == BAD_LOGGED {
        tracing::warn!("{key}: more undecodable payloads: counted, not logged");
    }
}

fn send_image(
    tx: &SyncSender<Arrival>,
    queued: &AtomicUsize,
    counts: &LiveCounts,
    t: f64,
    image: GrayImage,
) {
    if queued.fetch_add(1, Ordering::AcqRel) >= MAX_QUEUED_IMAGES {
        queued.fetch_sub(1, Ordering::AcqRel);
        counts.images_dropped.fetch_add(1, Ordering::Relaxed);
        return;
    }
    if tx.try_send(Arrival::Image(t, image)).is_err() {
        queued.fetch_sub(1, Ordering::AcqRel);
        counts.images_dropped.fetch_add(1, Ordering::Relaxed);
    }
}

/// The live samples in time order ([`LiveSensors::events`]).
pub struct LiveEvents {
    sensors: LiveSensors,
    stop: Arc<AtomicBool>,
    limits: LiveLimits,
    started: Instant,
    arrivals: ImageArrivals,
    last_arrival: Option<Instant>,
    newest_imu_t: f64,
    /// Images whose time the IMU has not reached, oldest first.
    held: VecDeque<(f64, GrayImage)>,
    ready: VecDeque<SimEvent>,
    ended: bool,
    /// The stamps' gap has been warned about.
    clock_warned: bool,
}

/// When each recent image arrived, by its stamp (s), oldest first.
pub type ImageArrivals = Arc<Mutex<VecDeque<(f64, Instant)>>>;

/// Image arrivals remembered for [`LiveEvents::arrivals`].
const MAX_ARRIVALS: usize = 256;

impl LiveEvents {
    /// When the recent images arrived: an estimate at an image's time was
    /// made that long after its image came off the network.
    pub fn arrivals(&self) -> ImageArrivals {
        Arc::clone(&self.arrivals)
    }

    /// Closes the session (on a helper thread, given up after `timeout`).
    pub fn close(self, timeout: Duration) {
        let session = self.sensors.session.clone();
        drop(self.sensors);
        let (done, finished) = std::sync::mpsc::channel();
        let spawned = std::thread::Builder::new()
            .name("zenoh-close".into())
            .spawn(move || {
                let _ = done.send(session.close().wait());
            });
        if spawned.is_ok() && finished.recv_timeout(timeout).is_err() {
            tracing::warn!("the Zenoh session did not close within {timeout:?}");
        }
    }

    fn arrive(&mut self, a: Arrival) {
        match a {
            Arrival::Imu(s) => {
                self.ready.push_back(SimEvent::Imu(s));
                self.newest_imu_t = self.newest_imu_t.max(s.t);
                while self
                    .held
                    .front()
                    .is_some_and(|(t, _)| *t <= self.newest_imu_t)
                {
                    if let Some((t, img)) = self.held.pop_front() {
                        self.ready.push_back(camera_event(t, img));
                    }
                }
            }
            Arrival::Image(t, img) => {
                self.sensors.queued_images.fetch_sub(1, Ordering::AcqRel);
                if let Ok(mut a) = self.arrivals.lock() {
                    if a.len() == MAX_ARRIVALS {
                        a.pop_front();
                    }
                    a.push_back((t, Instant::now()));
                }
                self.check_clocks(t);
                if t <= self.newest_imu_t {
                    self.ready.push_back(camera_event(t, img));
                    return;
                }
                let at = self.held.partition_point(|(h, _)| *h <= t);
                self.held.insert(at, (t, img));
                if self.held.len() > MAX_HELD_IMAGES {
                    self.held.pop_front();
                    self.sensors
                        .counts
                        .images_dropped
                        .fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }

    /// Notes how far an image's stamp is from the newest IMU sample's when
    /// it arrives (a few milliseconds when the two share a clock), and says
    /// once, loudly, when it is more than [`CLOCK_GAP_S`]: images far ahead
    /// of the IMU wait for it until they are dropped, images far behind are
    /// older than the filter, and either way nothing is estimated.
    fn check_clocks(&mut self, t: f64) {
        if !self.newest_imu_t.is_finite() {
            return;
        }
        let gap = t - self.newest_imu_t;
        let gap_ms = (gap.abs() * 1e3).min(u64::MAX as f64) as u64;
        self.sensors
            .counts
            .clock_gap_ms
            .fetch_max(gap_ms, Ordering::Relaxed);
        if gap.abs() > CLOCK_GAP_S && !self.clock_warned {
            self.clock_warned = true;
            tracing::warn!(
                "an image stamped {t:.3} s arrived {:.3} s {} the newest IMU sample: \
                 are the camera and the IMU stamped on one clock?",
                gap.abs(),
                if gap > 0.0 { "ahead of" } else { "behind" }
            );
        }
    }

    fn should_end(&self) -> bool {
        if self.stop.load(Ordering::Relaxed) {
            return true;
        }
        if self
            .limits
            .max_duration
            .is_some_and(|d| self.started.elapsed() >= d)
        {
            return true;
        }
        match self.last_arrival {
            Some(at) => at.elapsed() >= self.limits.idle,
            None => self.started.elapsed() >= self.limits.wait_first,
        }
    }
}

impl Iterator for LiveEvents {
    type Item = Result<SimEvent, String>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(ev) = self.ready.pop_front() {
                return Some(Ok(ev));
            }
            if self.ended {
                let (t, img) = self.held.pop_front()?;
                return Some(Ok(camera_event(t, img)));
            }
            if self.should_end() {
                self.ended = true;
                continue;
            }
            match self.sensors.rx.recv_timeout(Duration::from_millis(100)) {
                Ok(a) => {
                    self.last_arrival = Some(Instant::now());
                    self.arrive(a);
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => self.ended = true,
            }
        }
    }
}

/// A camera event of a live image: no features yet (the frontend makes
/// them), no truth (a NaN time says so).
fn camera_event(t: f64, image: GrayImage) -> SimEvent {
    SimEvent::Camera(Box::new(CameraEvent {
        frame: FeatureFrame {
            t,
            camera: 0,
            features: Vec::new(),
        },
        truth: TruthState {
            t: f64::NAN,
            rot: Matrix3::identity(),
            pos: Vector3::zeros(),
            vel: Vector3::zeros(),
            biases: Biases::default(),
        },
        landmark_ids: Vec::new(),
        outlier: Vec::new(),
        image: Some(Arc::new(image)),
    }))
}

/// Latencies kept for the figures (8 MiB): a long run must not grow them
/// without bound.
const MAX_LATENCIES: usize = 1 << 20;

/// An estimate this close to an image's stamp is that image's, s: the
/// camera-IMU time offset the filter estimates is far below a frame period.
const SAME_IMAGE_S: f64 = 0.005;

/// How long after its image came off the network each estimate was made.
#[derive(Debug)]
pub struct EstimateLatency {
    arrivals: ImageArrivals,
    ms: Vec<f64>,
}

impl EstimateLatency {
    /// Latencies against the image arrivals of [`LiveEvents::arrivals`].
    pub fn new(arrivals: ImageArrivals) -> Self {
        Self {
            arrivals,
            ms: Vec::new(),
        }
    }

    /// An estimate at `t_s` (the image's time plus the estimated camera-IMU
    /// offset) was just made: its image's latency is kept, and the arrivals
    /// before it are forgotten.
    pub fn estimated(&mut self, t_s: f64) {
        let Ok(mut a) = self.arrivals.lock() else {
            return;
        };
        let mut image_arrived = None;
        while let Some(&(t, at)) = a.front() {
            if t > t_s + SAME_IMAGE_S {
                break;
            }
            a.pop_front();
            if (t - t_s).abs() <= SAME_IMAGE_S {
                image_arrived = Some(at);
            }
        }
        if let Some(at) = image_arrived.filter(|_| self.ms.len() < MAX_LATENCIES) {
            self.ms.push(at.elapsed().as_secs_f64() * 1e3);
        }
    }

    /// Mean and 95th percentile, for the console.
    pub fn line(&self) -> String {
        if self.ms.is_empty() {
            return "no estimate matched an image's arrival".into();
        }
        let mut ms = self.ms.clone();
        ms.sort_by(f64::total_cmp);
        let mean = ms.iter().sum::<f64>() / ms.len() as f64;
        let p95 = ms[((ms.len() - 1) as f64 * 0.95).round() as usize];
        format!(
            "an estimate {mean:.1} ms (p95 {p95:.1}) after its image arrived, over {} images",
            ms.len()
        )
    }
}

/// Publishes a robot's estimate, as a pose ([`LiveSensors::pose_publisher`])
/// or an odometry ([`LiveSensors::odometry_publisher`]).
pub struct PosePublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
    frame_id: String,
    /// The body's frame id: `nav_msgs/Odometry` when set, else
    /// `geometry_msgs/PoseWithCovarianceStamped`.
    child_frame_id: Option<String>,
    /// Messages published.
    pub sent: u64,
    /// Messages the session refused (logged once).
    pub failed: u64,
}

impl PosePublisher {
    /// Publishes `pose` with its covariance, and with `twist` for an odometry.
    pub fn publish(&mut self, pose: &StampedPose, cov: &StampedCovariance, twist: &BodyTwist) {
        let covariance = ros_cdr::ros_pose_covariance(pose, cov);
        let header = Header::at(pose.t, &self.frame_id);
        let payload = match &self.child_frame_id {
            None => ros_cdr::encode_pose(&header, pose, &covariance),
            Some(child) => {
                let mut twist_cov = [0.0; 36];
                for r in 0..6 {
                    for c in 0..6 {
                        twist_cov[6 * r + c] = twist.cov[(r, c)];
                    }
                }
                let ros_twist = ros_cdr::RosTwist {
                    linear: twist.linear,
                    angular: twist.angular,
                    covariance: twist_cov,
                };
                ros_cdr::encode_odometry(&header, child, pose, &covariance, &ros_twist)
            }
        };
        match self.publisher.put(payload).wait() {
            Ok(()) => self.sent += 1,
            Err(e) => {
                if self.failed == 0 {
                    tracing::warn!("pose not published: {e}");
                }
                self.failed += 1;
            }
        }
    }
}

/// How a sequence is published.
#[derive(Clone, Debug)]
pub struct PublishOptions {
    /// Playback speed (1: as recorded).
    pub speed: f64,
    /// IMU samples published before the first image, s (a static start
    /// needs a still window before it).
    pub imu_lead_s: f64,
    /// Wait this long for a subscriber to both keys before publishing.
    pub wait_subscriber: Duration,
}

/// What [`publish_sequence`] sent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Published {
    /// IMU messages.
    pub imu: u64,
    /// Image messages.
    pub images: u64,
    /// Images that could not be read (skipped).
    pub images_skipped: u64,
}

/// Publishes `ds` on `keys` as ROS 2 messages (little-endian CDR, `mono8`
/// images): its images and the IMU samples from `imu_lead_s` before the first
/// image to the last, paced by their stamps over `speed`. Waits for a
/// subscriber to both keys first (the samples would be lost otherwise), and
/// ends early when `stop` is set.
pub fn publish_sequence(
    ds: &EurocDataset,
    settings: &ZenohSettings,
    keys: &SensorKeys,
    opts: &PublishOptions,
    stop: &AtomicBool,
) -> Result<Published, LiveError> {
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(LiveError::Setting(format!(
            "speed {} must be a positive number",
            opts.speed
        )));
    }
    let (Some(first), Some(last)) = (ds.images.first(), ds.images.last()) else {
        return Err(LiveError::Setting("the sequence has no images".into()));
    };
    let (from, to) = (first.t - opts.imu_lead_s.max(0.0), last.t);
    let config = crate::transport::zenoh::load_config(settings).map_err(zenoh_error)?;
    let session = zenoh::open(config).wait().map_err(zenoh_error)?;
    let declare = |key: &str| {
        session
            .declare_publisher(key.to_owned())
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(zenoh_error)
    };
    let (imu_pub, image_pub) = (declare(&keys.imu)?, declare(&keys.image)?);
    let waited = Instant::now();
    loop {
        let matched = |p: &zenoh::pubsub::Publisher<'_>| {
            p.matching_status().wait().is_ok_and(|s| s.matching())
        };
        if matched(&imu_pub) && matched(&image_pub) {
            break;
        }
        if waited.elapsed() >= opts.wait_subscriber || stop.load(Ordering::Relaxed) {
            return Err(LiveError::Setting(format!(
                "no subscriber to both {} and {} within {:?}",
                keys.imu, keys.image, opts.wait_subscriber
            )));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut sent = Published::default();
    let start = Instant::now();
    let pace = |t: f64| {
        let due = Duration::from_secs_f64(((t - from) / opts.speed).max(0.0));
        if let Some(wait) = due.checked_sub(start.elapsed()) {
            std::thread::sleep(wait);
        }
    };
    for ev in ds.events() {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        match ev {
            Ok(SimEvent::Imu(s)) if s.t >= from && s.t <= to => {
                pace(s.t);
                let payload = ros_cdr::encode_imu(&Header::at(s.t, "imu0"), &s);
                imu_pub.put(payload).wait().map_err(zenoh_error)?;
                sent.imu += 1;
            }
            Ok(SimEvent::Imu(_)) => {}
            Ok(SimEvent::Camera(c)) => {
                let Some(img) = c.image.as_deref() else {
                    continue;
                };
                pace(c.frame.t);
                let payload = ros_cdr::encode_mono8(&Header::at(c.frame.t, "cam0"), img);
                image_pub.put(payload).wait().map_err(zenoh_error)?;
                sent.images += 1;
            }
            Err(e) => {
                tracing::warn!("image skipped: {e}");
                sent.images_skipped += 1;
            }
        }
    }
    // Let the last samples leave before the session goes.
    std::thread::sleep(Duration::from_millis(300));
    drop((imu_pub, image_pub));
    session.close().wait().map_err(zenoh_error)?;
    Ok(sent)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn imu(t: f64) -> Arrival {
        Arrival::Imu(ImuSample {
            t,
            gyro: Vector3::zeros(),
            accel: Vector3::new(0.0, 0.0, 9.81),
        })
    }

    fn image(t: f64) -> Arrival {
        Arrival::Image(t, GrayImage::new(2, 2, vec![0; 4]).expect("image"))
    }

    fn times(ev: &LiveEvents) -> Vec<(char, f64)> {
        ev.ready
            .iter()
            .map(|e| match e {
                SimEvent::Imu(s) => ('i', s.t),
                SimEvent::Camera(c) => ('c', c.frame.t),
            })
            .collect()
    }

    /// Images that arrive before the IMU reaches their time wait for it, in
    /// time order; the held images are bounded.
    #[test]
    fn images_wait_for_the_imu_to_reach_their_time() {
        let settings = ZenohSettings {
            config: "loopback".into(),
            listen: vec!["tcp/127.0.0.1:0".into()],
            connect: Vec::new(),
            robot_certificates: None,
        };
        let keys = SensorKeys {
            imu: "test/live/imu".into(),
            image: "test/live/image".into(),
        };
        let sensors = LiveSensors::open(&settings, &keys).expect("session");
        let limits = LiveLimits {
            wait_first: Duration::ZERO,
            idle: Duration::ZERO,
            max_duration: None,
        };
        let mut ev = sensors.events(Arc::new(AtomicBool::new(false)), limits);
        // As the channel would deliver them (the counter of queued images too).
        ev.sensors.queued_images.store(3, Ordering::Relaxed);
        for a in [
            imu(0.0),
            image(0.1),
            image(0.05),
            imu(0.04),
            imu(0.08),
            image(0.08),
        ] {
            ev.arrive(a);
        }
        assert_eq!(
            times(&ev),
            vec![
                ('i', 0.0),
                ('i', 0.04),
                ('i', 0.08),
                ('c', 0.05),
                ('c', 0.08)
            ]
        );
        ev.arrive(imu(0.12));
        assert_eq!(times(&ev)[5..], [('i', 0.12), ('c', 0.1)]);
        assert_eq!(ev.sensors.queued_images.load(Ordering::Relaxed), 0);
        // An IMU that stops: the held images stay bounded, the oldest dropped.
        ev.sensors
            .queued_images
            .store(MAX_HELD_IMAGES + 5, Ordering::Relaxed);
        for k in 0..MAX_HELD_IMAGES + 5 {
            ev.arrive(image(1.0 + k as f64));
        }
        assert_eq!(ev.held.len(), MAX_HELD_IMAGES);
        assert_eq!(ev.sensors.counts.images_dropped.load(Ordering::Relaxed), 5);
        // Those images ran up to 36.88 s ahead of the IMU's 0.12 s: noted and
        // warned about.
        assert!(ev.clock_warned);
        assert_eq!(
            ev.sensors.counts.clock_gap_ms.load(Ordering::Relaxed),
            36_880
        );
        // The run ends (limits of zero): the held images come last, in order.
        ev.ready.clear();
        let rest: Vec<f64> = ev
            .by_ref()
            .map(|e| match e {
                Ok(SimEvent::Camera(c)) => c.frame.t,
                _ => f64::NAN,
            })
            .collect();
        assert_eq!(rest.len(), MAX_HELD_IMAGES);
        assert!(rest.windows(2).all(|w| w[0] < w[1]) && rest[0] == 6.0);
        ev.close(Duration::from_secs(5));
    }
}
