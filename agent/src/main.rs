//! `agent`: runs one robot of the fleet.
use clap::Parser;

/// One robot's agent of the distributed multi-robot VIO fleet.
///
/// The estimator and transports arrive in later versions; this binary currently
/// reports its version and options.
#[derive(Parser, Debug)]
#[command(name = "agent", version, about, long_about = None)]
struct Cli {}

fn main() -> anyhow::Result<()> {
    let _cli = Cli::parse();
    println!("agent {}", env!("CARGO_PKG_VERSION"));
    Ok(())
}
