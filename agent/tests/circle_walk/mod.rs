//! A walk on a 3 m circle looking along it, with a speed profile: what the
//! standstill tests share (TUM text, 20 Hz, times from 100 s).

/// Writes `steps` poses 0.05 s apart to `path`: the walk covers 1.5 m/s times
/// `speed(t)` (t from 0), turns `angle_per_m` rad per metre walked around the
/// circle's centre and bobs 0.2 m up and down.
pub fn write_circle_walk(
    path: &std::path::Path,
    steps: usize,
    angle_per_m: f64,
    speed: impl Fn(f64) -> f64,
) {
    write_walk(path, steps, 3.0, angle_per_m, speed);
}

/// As [`write_circle_walk`] on a circle of `radius_m` (300 m with
/// `angle_per_m` 1/300 is a straight walk as far as an IMU can tell: 0.005
/// rad/s at full speed).
pub fn write_walk(
    path: &std::path::Path,
    steps: usize,
    radius_m: f64,
    angle_per_m: f64,
    speed: impl Fn(f64) -> f64,
) {
    let mut text = String::from("# timestamp tx ty tz qx qy qz qw\n");
    let mut s: f64 = 0.0;
    for k in 0..=steps {
        let t = k as f64 * 0.05;
        let a = angle_per_m * s;
        let (x, y, z) = (
            radius_m * a.cos(),
            radius_m * a.sin(),
            1.0 + 0.2 * (0.5 * s).sin(),
        );
        let yaw: f64 = a + 1.57;
        text.push_str(&format!(
            "{:.3} {x:.6} {y:.6} {z:.6} 0 0 {:.9} {:.9}\n",
            100.0 + t,
            (yaw / 2.0).sin(),
            (yaw / 2.0).cos()
        ));
        s += speed(t) * 0.05 * 1.5;
    }
    std::fs::write(path, text).expect("write trajectory");
}
