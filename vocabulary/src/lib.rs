//! A DBoW2-style bag-of-binary-words vocabulary for 256-bit descriptors.
//!
//! - [`tree`]: the vocabulary tree, built top-down by k-majority clustering
//!   ([`cluster`]) with k-means++ seeding; its leaves are the words.
//! - [`weights`]: IDF weights learnt from the training images.
//! - [`vocabulary`]: tree and weights together ([`Vocabulary::train`]).
//! - [`bow`]: an image's BoW vector and direct index, and the L1 score.
//! - [`database`]: images with an inverted index, queried by score.
//! - [`matching`]: descriptor matching restricted by direct indices.
//! - [`io`]: vocabulary files (header + bincode, validated on load).
//! - [`text`]: the hex text format of descriptor sets; [`simdata`]: images from
//!   the fleet simulator.
#![warn(missing_docs)]

pub mod bow;
pub mod cluster;
pub mod database;
pub mod io;
pub mod matching;
pub mod simdata;
pub mod synthetic;
pub mod text;
pub mod tree;
pub mod vocabulary;
pub mod weights;

pub use bow::{l1_score, BowVector, FeatureVector};
pub use common::descriptor::Descriptor;
pub use database::{Database, Entry, EntryId};
pub use io::{FormatError, VocabIoError};
pub use matching::{match_brute_force, match_features, MatchParams};
pub use tree::{NodeId, TrainError, TrainParams, VocabularyTree, WordId};
pub use vocabulary::{InvalidVocabulary, Vocabulary};
