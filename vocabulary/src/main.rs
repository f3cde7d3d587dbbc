//! `vocab`: train, inspect and try out bag-of-binary-words vocabularies.

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;
use vocabulary::simdata::simulate_images;
use vocabulary::text::{read_images, write_images};
use vocabulary::{Database, Descriptor, TrainParams, Vocabulary};

#[derive(Parser, Debug)]
#[command(
    name = "vocab",
    version,
    about = "Bag-of-binary-words vocabularies (DBoW2-style)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Shape of the tree and clustering seed.
#[derive(Args, Debug)]
struct TreeArgs {
    /// Branching factor k.
    #[arg(long, default_value_t = 10)]
    k: usize,
    /// Depth L (at most k^L words).
    #[arg(long, default_value_t = 4)]
    levels: usize,
    /// Iteration cap of each k-majority clustering.
    #[arg(long, default_value_t = 20)]
    max_iterations: usize,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Train a vocabulary from a text file: one image per line, descriptors as 64
    /// hex characters separated by spaces.
    Train {
        /// The descriptor file.
        #[arg(long)]
        descriptors: PathBuf,
        #[command(flatten)]
        tree: TreeArgs,
        /// Seed of the k-means++ seeding.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where to write the vocabulary.
        #[arg(long)]
        out: PathBuf,
    },
    /// Train a vocabulary on simulated frames: every N-th camera frame of every
    /// robot of a fleet scenario is one training image.
    TrainSim {
        /// The scenario (YAML).
        #[arg(long)]
        scenario: PathBuf,
        /// Simulation seed (default: the scenario's).
        #[arg(long)]
        seed: Option<u64>,
        /// Keep every N-th frame of each robot.
        #[arg(long, default_value_t = 5)]
        every: usize,
        #[command(flatten)]
        tree: TreeArgs,
        /// Seed of the k-means++ seeding.
        #[arg(long, default_value_t = 1)]
        train_seed: u64,
        /// Also write the training images as a descriptor text file.
        #[arg(long)]
        save_descriptors: Option<PathBuf>,
        /// Where to write the vocabulary.
        #[arg(long)]
        out: PathBuf,
    },
    /// Print a vocabulary's shape.
    Info {
        /// The vocabulary file.
        vocab: PathBuf,
    },
    /// For each image (line) of a descriptor file, print the best other image and
    /// its score.
    Query {
        /// The vocabulary file.
        #[arg(long)]
        vocab: PathBuf,
        /// The descriptor file.
        #[arg(long)]
        descriptors: PathBuf,
    },
}

fn train(images: &[Vec<Descriptor>], tree: &TreeArgs, seed: u64, out: &Path) -> Result<()> {
    let params = TrainParams {
        k: tree.k,
        levels: tree.levels,
        seed,
        max_iterations: tree.max_iterations,
    };
    let descriptors: usize = images.iter().map(Vec::len).sum();
    let start = Instant::now();
    let vocab = Vocabulary::train(images, &params)?;
    vocab.save(out)?;
    println!(
        "trained k={} L={}: {} words from {} images ({} descriptors) in {:.2} s -> {}",
        vocab.k(),
        vocab.levels(),
        vocab.word_count(),
        vocab.training_images(),
        descriptors,
        start.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

fn info(path: &Path) -> Result<()> {
    let vocab = Vocabulary::load(path)?;
    let weighted = vocab.weights().iter().filter(|w| **w > 0.0).count();
    println!("file: {}", path.display());
    println!("k: {}", vocab.k());
    println!("L: {}", vocab.levels());
    println!("nodes: {}", vocab.tree().nodes().len());
    println!("words: {}", vocab.word_count());
    println!("words with positive weight: {weighted}");
    println!("training images: {}", vocab.training_images());
    Ok(())
}

fn query(vocab_path: &Path, descriptors: &Path) -> Result<()> {
    let vocab = Arc::new(Vocabulary::load(vocab_path)?);
    let images = read_images(descriptors)?;
    if images.len() < 2 {
        bail!("{} holds fewer than two images", descriptors.display());
    }
    let mut db = Database::new(Arc::clone(&vocab), 2);
    for image in &images {
        db.add(image);
    }
    let mut out = std::io::stdout().lock();
    writeln!(out, "image best_other score")?;
    for (i, image) in images.iter().enumerate() {
        let best = db
            .query(image, 2)
            .into_iter()
            .find(|(e, _)| e.0 as usize != i);
        match best {
            Some((e, s)) => writeln!(out, "{i} {e} {s:.4}")?,
            None => writeln!(out, "{i} - 0")?,
        }
    }
    Ok(())
}

fn main() -> std::process::ExitCode {
    common::exit_report::exit_code(run_main())
}

fn run_main() -> Result<()> {
    match run() {
        // A closed pipe (`vocab query ... | head`) is not an error.
        Err(e)
            if e.downcast_ref::<std::io::Error>()
                .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe) =>
        {
            Ok(())
        }
        other => other,
    }
}

fn run() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Train {
            descriptors,
            tree,
            seed,
            out,
        } => {
            let images = read_images(&descriptors)?;
            train(&images, &tree, seed, &out)
        }
        Command::TrainSim {
            scenario,
            seed,
            every,
            tree,
            train_seed,
            save_descriptors,
            out,
        } => {
            let start = Instant::now();
            let sim = simulate_images(&scenario, seed, every)
                .with_context(|| format!("simulating {}", scenario.display()))?;
            let images: Vec<Vec<Descriptor>> = sim.into_iter().map(|i| i.descriptors).collect();
            println!(
                "simulated {} training images in {:.2} s",
                images.len(),
                start.elapsed().as_secs_f64()
            );
            if let Some(path) = save_descriptors {
                write_images(&path, &images)?;
            }
            train(&images, &tree, train_seed, &out)
        }
        Command::Info { vocab } => info(&vocab),
        Command::Query { vocab, descriptors } => query(&vocab, &descriptors),
    }
}
