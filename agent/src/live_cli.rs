//! `agent live`: a robot's own IMU and camera, live over Zenoh as ROS 2
//! topics ([`crate::ros_input`]), through the image frontend and the
//! estimator from a static start, with the outputs of `agent dataset`.
//! The calibration is a folder in the EuRoC / Kalibr layout
//! (`cam0/sensor.yaml`, `imu0/sensor.yaml`).

use crate::dataset::{mav0_root, SensorSetup};
use crate::dataset_cli::{dataset_options, frontend_options, StreamRun};
use crate::dataset_run::StreamSensors;
use crate::ros_input::{EstimateLatency, LiveLimits, LiveSensors, ZenohArgs};
use anyhow::{bail, Context, Result};
use common::trajectory::read_euroc_csv;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Arguments of `agent live`.
#[derive(clap::Args, Debug)]
pub struct LiveArgs {
    /// The session and the sensors' keys.
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// The calibration: a folder with `cam0/sensor.yaml` and
    /// `imu0/sensor.yaml` (EuRoC / Kalibr layout; `mav0` inside it is found).
    #[arg(long)]
    pub sensors: PathBuf,
    /// Ground truth (EuRoC CSV, on the sensors' clock) to score against.
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Estimator settings (YAML), as for `agent dataset`.
    #[arg(long, value_name = "YAML")]
    pub estimator: Option<PathBuf>,
    /// Image frontend settings (YAML), as for `agent dataset`.
    #[arg(long, value_name = "YAML")]
    pub frontend: Option<PathBuf>,
    /// Output folder.
    #[arg(long, default_value = "out/live")]
    pub out: PathBuf,
    /// Log every this many images (with their tracks) to `agent.mcap`.
    #[arg(long, default_value_t = 5)]
    pub mcap_image_every: usize,
    /// Wait this long for the first sensor message, s.
    #[arg(long, default_value_t = 60.0)]
    pub wait_s: f64,
    /// End when no sensor message arrived for this long, s (SIGINT or SIGTERM
    /// end the run too; its outputs are written either way).
    #[arg(long, default_value_t = 5.0)]
    pub idle_timeout_s: f64,
    /// End after this long in any case, s.
    #[arg(long)]
    pub max_duration_s: Option<f64>,
    /// Where the estimated pose goes, after every frame
    /// (`geometry_msgs/msg/PoseWithCovarianceStamped`; `none`: nowhere).
    #[arg(long, default_value = "vio/pose")]
    pub pose_key: String,
    /// The frame id of the published poses: the world the static start
    /// defines (gravity along -z, origin and yaw at the start).
    #[arg(long, default_value = "vio_world")]
    pub world_frame: String,
    /// Where the estimate goes as an odometry, after every frame
    /// (`nav_msgs/msg/Odometry`: the pose in `--world-frame`, the velocity and
    /// angular rate in `--body-frame`, each with its covariance; `none`:
    /// nowhere).
    #[arg(long, default_value = "vio/odom")]
    pub odom_key: String,
    /// The odometry's `child_frame_id`: the IMU, whose axes the twist is in.
    #[arg(long, default_value = "imu")]
    pub body_frame: String,
}

fn seconds(name: &str, s: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(s)
        .with_context(|| format!("--{name} {s}: not a duration in seconds"))
}

/// Runs the command until the sensors stop, the time is up or `stop` is set.
pub fn run_live_command(args: &LiveArgs, stop: Arc<AtomicBool>) -> Result<()> {
    let wall = Instant::now();
    let root = mav0_root(&args.sensors);
    let setup = SensorSetup::load(&root)
        .with_context(|| format!("reading the calibration in {}", root.display()))?;
    let groundtruth = args
        .groundtruth
        .as_deref()
        .map(read_euroc_csv)
        .transpose()
        .context("reading the ground truth")?;
    let (opts, variant) = dataset_options(setup.imu_noise, args.estimator.as_deref())?;
    let frontend = frontend_options(args.frontend.as_deref())?;
    let limits = LiveLimits {
        wait_first: seconds("wait-s", args.wait_s)?,
        idle: seconds("idle-timeout-s", args.idle_timeout_s)?,
        max_duration: args
            .max_duration_s
            .map(|s| seconds("max-duration-s", s))
            .transpose()?,
    };
    let keys = args.zenoh.keys();
    let live = LiveSensors::open(&args.zenoh.settings(), &keys).context("opening the sensors")?;
    let counts = live.counts();
    let mut poses = match args.pose_key.as_str() {
        "none" => None,
        key => Some(
            live.pose_publisher(key, &args.world_frame)
                .with_context(|| format!("publishing poses on {key}"))?,
        ),
    };
    let mut odometry = match args.odom_key.as_str() {
        "none" => None,
        key => Some(
            live.odometry_publisher(key, &args.world_frame, &args.body_frame)
                .with_context(|| format!("publishing odometry on {key}"))?,
        ),
    };
    tracing::info!(
        "{}: listening for {} (IMU) and {} (camera)",
        variant.name(),
        keys.imu,
        keys.image
    );
    let run = StreamRun {
        out: &args.out,
        name: "live".into(),
        sensors: StreamSensors {
            calibration: &setup.calibration,
            groundtruth: groundtruth.as_deref(),
        },
        opts,
        variant,
        frontend,
        mcap_image_every: args.mcap_image_every,
        wall,
    };
    let mut events = live.events(stop, limits);
    let mut latency = EstimateLatency::new(events.arrivals());
    let result = run.run(&mut events, |record| {
        let (Some(pose), Some(cov), Some(twist)) = (
            record.estimate.last(),
            record.covariance.last(),
            record.last_twist.as_ref(),
        ) else {
            return;
        };
        for p in [poses.as_mut(), odometry.as_mut()].into_iter().flatten() {
            p.publish(pose, cov, twist);
        }
        latency.estimated(pose.t);
    });
    events.close(Duration::from_secs(5));
    println!("sensors: {}", counts.line());
    if let Some(p) = &poses {
        println!(
            "poses: {} published on {} ({} refused); {}",
            p.sent,
            args.pose_key,
            p.failed,
            latency.line()
        );
    }
    if let Some(p) = &odometry {
        println!(
            "odometry: {} published on {} ({} refused)",
            p.sent, args.odom_key, p.failed
        );
    }
    if counts.nothing_received() {
        bail!(
            "no sensor message decoded on {} or {} within {} s",
            keys.imu,
            keys.image,
            args.wait_s
        );
    }
    result.map(|_| ())
}
