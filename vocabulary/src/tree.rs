//! The vocabulary tree: branching factor `k`, depth `L`, built top-down by
//! k-majority clustering; the leaves are the words.
//!
//! Nodes are stored flat in one `Vec`: node 0 is the root (depth 0, no center of
//! its own meaning), the children of a node are contiguous and always come after
//! it. A node becomes a leaf when it reaches depth `L`, when its descriptors are
//! all identical, or when clustering cannot split them, so leaves may sit above
//! depth `L` and a node may have fewer than `k` children.

use crate::cluster::{k_majority, majority};
use common::descriptor::Descriptor;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use thiserror::Error;

/// Index of a node in [`VocabularyTree::nodes`].
pub type NodeId = u32;
/// Index of a word (a leaf), `0..word_count`.
pub type WordId = u32;

/// Largest branching factor accepted (training and files).
pub const MAX_K: usize = 256;
/// Largest depth accepted (training and files).
pub const MAX_LEVELS: usize = 16;

/// How to train a tree.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TrainParams {
    /// Branching factor `k` (2..=[`MAX_K`]).
    pub k: usize,
    /// Depth `L` (1..=[`MAX_LEVELS`]): at most `k^L` words.
    pub levels: usize,
    /// Seed of the ChaCha RNG used for k-means++ seeding.
    pub seed: u64,
    /// Iteration cap of each k-majority clustering.
    pub max_iterations: usize,
}

impl Default for TrainParams {
    /// k = 10, L = 4 (at most 10 000 words), seed 1, 20 iterations.
    fn default() -> Self {
        Self {
            k: 10,
            levels: 4,
            seed: 1,
            max_iterations: 20,
        }
    }
}

/// Why a vocabulary could not be trained.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum TrainError {
    /// `k` is outside 2..=[`MAX_K`].
    #[error("branching factor k = {0} is outside 2..={MAX_K}")]
    BadK(usize),
    /// `levels` is outside 1..=[`MAX_LEVELS`].
    #[error("depth L = {0} is outside 1..={MAX_LEVELS}")]
    BadLevels(usize),
    /// There was nothing to cluster.
    #[error("no training descriptors")]
    NoDescriptors,
    /// The tree would need more nodes than a `u32` can index.
    #[error("the tree has too many nodes")]
    TooManyNodes,
}

/// One node of the tree.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Node {
    center: Descriptor,
    parent: Option<NodeId>,
    first_child: NodeId,
    child_count: u32,
    depth: u32,
    word: Option<WordId>,
}

impl Node {
    /// The cluster center (bitwise majority of the training descriptors under it).
    pub fn center(&self) -> &Descriptor {
        &self.center
    }
    /// The parent, `None` for the root.
    pub fn parent(&self) -> Option<NodeId> {
        self.parent
    }
    /// The children's ids (contiguous; empty for a leaf).
    pub fn children(&self) -> Range<NodeId> {
        self.first_child..self.first_child.saturating_add(self.child_count)
    }
    /// Depth below the root (root = 0).
    pub fn depth(&self) -> u32 {
        self.depth
    }
    /// The word id if this node is a leaf.
    pub fn word(&self) -> Option<WordId> {
        self.word
    }
    /// Whether this node is a leaf (a word).
    pub fn is_leaf(&self) -> bool {
        self.child_count == 0
    }
}

/// A hierarchical k-majority vocabulary tree.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VocabularyTree {
    k: u32,
    levels: u32,
    nodes: Vec<Node>,
    words: Vec<NodeId>,
}

/// One pending split during training.
struct Pending {
    node: NodeId,
    data: Vec<Descriptor>,
}

impl VocabularyTree {
    /// Trains a tree on `descriptors`. Deterministic: the same descriptors in the
    /// same order with the same parameters give the same tree.
    pub fn build(descriptors: &[Descriptor], params: &TrainParams) -> Result<Self, TrainError> {
        if !(2..=MAX_K).contains(&params.k) {
            return Err(TrainError::BadK(params.k));
        }
        if !(1..=MAX_LEVELS).contains(&params.levels) {
            return Err(TrainError::BadLevels(params.levels));
        }
        if descriptors.is_empty() {
            return Err(TrainError::NoDescriptors);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        let mut tree = VocabularyTree {
            k: params.k as u32,
            levels: params.levels as u32,
            nodes: vec![Node {
                center: majority(descriptors),
                parent: None,
                first_child: 0,
                child_count: 0,
                depth: 0,
                word: None,
            }],
            words: Vec::new(),
        };
        // Depth-first, children in order: a stack popped from the back with
        // children pushed in reverse.
        let mut stack = vec![Pending {
            node: 0,
            data: descriptors.to_vec(),
        }];
        while let Some(Pending { node, data }) = stack.pop() {
            let depth = tree.nodes[node as usize].depth;
            let splittable = depth < tree.levels && data.iter().any(|d| *d != data[0]);
            let clustering = if splittable {
                Some(k_majority(&data, params.k, params.max_iterations, &mut rng))
            } else {
                None
            };
            let Some(clustering) = clustering.filter(|c| c.centers.len() >= 2) else {
                let word = u32::try_from(tree.words.len()).map_err(|_| TrainError::TooManyNodes)?;
                tree.nodes[node as usize].word = Some(word);
                tree.words.push(node);
                continue;
            };
            let first = u32::try_from(tree.nodes.len()).map_err(|_| TrainError::TooManyNodes)?;
            let count = clustering.centers.len() as u32;
            first.checked_add(count).ok_or(TrainError::TooManyNodes)?;
            let mut parts: Vec<Vec<Descriptor>> = vec![Vec::new(); clustering.centers.len()];
            for (d, &a) in data.iter().zip(&clustering.assignment) {
                parts[a].push(*d);
            }
            for center in &clustering.centers {
                tree.nodes.push(Node {
                    center: *center,
                    parent: Some(node),
                    first_child: 0,
                    child_count: 0,
                    depth: depth + 1,
                    word: None,
                });
            }
            let n = &mut tree.nodes[node as usize];
            n.first_child = first;
            n.child_count = count;
            for (i, part) in parts.into_iter().enumerate().rev() {
                stack.push(Pending {
                    node: first + i as u32,
                    data: part,
                });
            }
            tracing::trace!(node, depth, children = count, "split");
        }
        tracing::debug!(
            nodes = tree.nodes.len(),
            words = tree.words.len(),
            "vocabulary tree built"
        );
        Ok(tree)
    }

    /// Branching factor `k`.
    pub fn k(&self) -> usize {
        self.k as usize
    }

    /// Depth `L`.
    pub fn levels(&self) -> usize {
        self.levels as usize
    }

    /// All nodes; index 0 is the root.
    pub fn nodes(&self) -> &[Node] {
        &self.nodes
    }

    /// One node, `None` if out of range.
    pub fn node(&self, id: NodeId) -> Option<&Node> {
        self.nodes.get(id as usize)
    }

    /// Number of words (leaves).
    pub fn word_count(&self) -> usize {
        self.words.len()
    }

    /// The leaf node of a word, `None` if out of range.
    pub fn word_node(&self, word: WordId) -> Option<NodeId> {
        self.words.get(word as usize).copied()
    }

    /// Nearest child of `node` (ties to the lowest id); `None` for a leaf.
    fn descend(&self, node: &Node, d: &Descriptor) -> Option<NodeId> {
        let mut best: Option<(NodeId, u32)> = None;
        for id in node.children() {
            let dist = self.nodes[id as usize].center.distance(d);
            if best.is_none_or(|(_, b)| dist < b) {
                best = Some((id, dist));
            }
        }
        best.map(|(id, _)| id)
    }

    /// The greedy path of `d` from the root to its leaf (root first).
    pub fn path(&self, d: &Descriptor) -> Vec<NodeId> {
        let mut path = vec![0];
        let mut id = 0;
        while let Some(next) = self.descend(&self.nodes[id as usize], d) {
            path.push(next);
            id = next;
        }
        path
    }

    /// The word of `d`: the leaf reached by descending greedily to the nearest
    /// child center.
    pub fn transform(&self, d: &Descriptor) -> WordId {
        self.transform_with_node(d, 0).0
    }

    /// The word of `d` and its ancestor `levels_up` levels above the leaf level:
    /// the node at depth `L - levels_up` on the greedy path (the leaf itself when
    /// the leaf is shallower; the root when `levels_up >= L`).
    pub fn transform_with_node(&self, d: &Descriptor, levels_up: usize) -> (WordId, NodeId) {
        let target = self
            .levels
            .saturating_sub(levels_up.min(u32::MAX as usize) as u32);
        let mut id: NodeId = 0;
        let mut at_level = if target == 0 { Some(0) } else { None };
        while let Some(next) = self.descend(&self.nodes[id as usize], d) {
            id = next;
            if self.nodes[id as usize].depth == target {
                at_level = Some(id);
            }
        }
        let node = &self.nodes[id as usize];
        (node.word.unwrap_or(0), at_level.unwrap_or(id))
    }

    /// Checks every structural invariant, so that a tree read from a file cannot
    /// make [`VocabularyTree::transform`] index out of range or loop.
    pub fn validate(&self) -> Result<(), String> {
        let k = self.k as usize;
        if !(2..=MAX_K).contains(&k) {
            return Err(format!("k = {k} is outside 2..={MAX_K}"));
        }
        let levels = self.levels as usize;
        if !(1..=MAX_LEVELS).contains(&levels) {
            return Err(format!("L = {levels} is outside 1..={MAX_LEVELS}"));
        }
        let n = self.nodes.len();
        if n == 0 {
            return Err("the tree has no nodes".into());
        }
        if n > u32::MAX as usize || self.words.len() > n {
            return Err(format!("{n} nodes, {} words: too many", self.words.len()));
        }
        let mut referenced = vec![false; n];
        for (i, node) in self.nodes.iter().enumerate() {
            match (i, node.parent) {
                (0, None) => {
                    if node.depth != 0 {
                        return Err("the root's depth is not 0".into());
                    }
                }
                (0, Some(_)) => return Err("the root has a parent".into()),
                (_, None) => return Err(format!("node {i} has no parent")),
                (_, Some(p)) => {
                    let parent = self
                        .nodes
                        .get(p as usize)
                        .ok_or_else(|| format!("node {i}: parent {p} out of range"))?;
                    if !parent.children().contains(&(i as u32)) {
                        return Err(format!("node {i} is not among its parent's children"));
                    }
                    if parent.depth.checked_add(1) != Some(node.depth) {
                        return Err(format!("node {i}: depth {} is inconsistent", node.depth));
                    }
                }
            }
            if node.depth > self.levels {
                return Err(format!("node {i} is deeper than L = {levels}"));
            }
            if node.child_count as usize > k {
                return Err(format!("node {i} has {} > k children", node.child_count));
            }
            if node.child_count > 0 {
                let end = u64::from(node.first_child) + u64::from(node.child_count);
                if node.first_child as usize <= i || end > n as u64 {
                    return Err(format!("node {i}: children out of range"));
                }
                for c in node.children() {
                    if std::mem::replace(&mut referenced[c as usize], true) {
                        return Err(format!("node {c} has two parents"));
                    }
                }
            }
            match node.word {
                Some(w) if node.is_leaf() => {
                    if self.words.get(w as usize) != Some(&(i as u32)) {
                        return Err(format!("leaf {i}: word {w} does not point back"));
                    }
                }
                None if !node.is_leaf() => {}
                _ => return Err(format!("node {i}: word and leaf status disagree")),
            }
        }
        if referenced[0] || referenced[1..].iter().any(|r| !r) {
            return Err("the nodes do not form one tree".into());
        }
        for (w, &node) in self.words.iter().enumerate() {
            match self.nodes.get(node as usize).and_then(|n| n.word) {
                Some(back) if back as usize == w => {}
                _ => return Err(format!("word {w}: leaf {node} does not point back")),
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    fn random_descriptors(n: usize, seed: u64) -> Vec<Descriptor> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
            .collect()
    }

    fn params(k: usize, levels: usize) -> TrainParams {
        TrainParams {
            k,
            levels,
            ..TrainParams::default()
        }
    }

    #[test]
    fn k4_l3_tree_has_at_most_64_leaves_and_greedy_paths() {
        let data = random_descriptors(2000, 11);
        let tree = VocabularyTree::build(&data, &params(4, 3)).unwrap();
        tree.validate().unwrap();
        assert!(tree.word_count() <= 64);
        assert!(tree.word_count() >= 50, "{} words", tree.word_count());
        let leaves = tree.nodes().iter().filter(|n| n.is_leaf()).count();
        assert_eq!(leaves, tree.word_count());
        for d in &data {
            let word = tree.transform(d);
            let leaf = tree.word_node(word).unwrap();
            // Walk up from the leaf: at every level the node taken is the nearest
            // of its siblings (lowest id on ties).
            let mut id = leaf;
            let mut up = vec![id];
            while let Some(p) = tree.node(id).unwrap().parent() {
                let parent = tree.node(p).unwrap();
                let best = parent
                    .children()
                    .min_by_key(|&c| (tree.node(c).unwrap().center().distance(d), c))
                    .unwrap();
                assert_eq!(best, id);
                id = p;
                up.push(id);
            }
            assert_eq!(id, 0);
            up.reverse();
            assert_eq!(up, tree.path(d));
            assert!(up.len() <= 4);
        }
    }

    #[test]
    fn training_is_deterministic_per_seed() {
        let data = random_descriptors(1500, 12);
        let a = VocabularyTree::build(&data, &params(5, 3)).unwrap();
        let b = VocabularyTree::build(&data, &params(5, 3)).unwrap();
        assert_eq!(a, b);
        let c = VocabularyTree::build(
            &data,
            &TrainParams {
                seed: 99,
                ..params(5, 3)
            },
        )
        .unwrap();
        assert_ne!(a, c);
    }

    #[test]
    fn degenerate_training_sets() {
        let one = random_descriptors(1, 1);
        let t = VocabularyTree::build(&one, &params(10, 4)).unwrap();
        t.validate().unwrap();
        assert_eq!(t.word_count(), 1);
        assert_eq!(t.transform(&one[0]), 0);

        let few = random_descriptors(3, 2);
        let t = VocabularyTree::build(&few, &params(10, 4)).unwrap();
        t.validate().unwrap();
        assert_eq!(t.word_count(), 3);
        let words: std::collections::BTreeSet<_> = few.iter().map(|d| t.transform(d)).collect();
        assert_eq!(words.len(), 3);

        let mut dup = vec![Descriptor([5, 6, 7, 8]); 100];
        dup.extend(vec![Descriptor([1, 2, 3, 4]); 100]);
        let t = VocabularyTree::build(&dup, &params(10, 4)).unwrap();
        t.validate().unwrap();
        assert_eq!(t.word_count(), 2);

        assert_eq!(
            VocabularyTree::build(&[], &params(10, 4)),
            Err(TrainError::NoDescriptors)
        );
        assert_eq!(
            VocabularyTree::build(&one, &params(1, 4)),
            Err(TrainError::BadK(1))
        );
        assert_eq!(
            VocabularyTree::build(&one, &params(4, 0)),
            Err(TrainError::BadLevels(0))
        );
    }

    #[test]
    fn node_at_level_is_on_the_path() {
        let data = random_descriptors(3000, 13);
        let tree = VocabularyTree::build(&data, &params(6, 4)).unwrap();
        for d in data.iter().take(200) {
            let path = tree.path(d);
            for up in 0..6 {
                let (w, node) = tree.transform_with_node(d, up);
                assert_eq!(Some(*path.last().unwrap()), tree.word_node(w));
                let depth = 4usize.saturating_sub(up);
                let expect = path.get(depth).copied().unwrap_or(*path.last().unwrap());
                assert_eq!(node, expect, "levels_up {up}");
            }
        }
    }

    #[test]
    fn validate_rejects_broken_trees() {
        let data = random_descriptors(500, 14);
        let tree = VocabularyTree::build(&data, &params(4, 3)).unwrap();
        let mut t = tree.clone();
        t.nodes[0].first_child = 10_000;
        assert!(t.validate().is_err());
        let mut t = tree.clone();
        t.nodes[1].parent = Some(2);
        assert!(t.validate().is_err());
        let mut t = tree.clone();
        t.words.swap(0, 1);
        assert!(t.validate().is_err());
        let mut t = tree.clone();
        t.k = 1;
        assert!(t.validate().is_err());
        let mut t = tree.clone();
        t.nodes[0].first_child = 0; // self loop
        assert!(t.validate().is_err());
    }
}
