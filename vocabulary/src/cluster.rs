//! Binary clustering: k-majority (k-medians in Hamming space, the center of a
//! cluster is the bitwise majority of its members) with k-means++ seeding.
//!
//! Every random draw comes from the caller's RNG, so the result is a pure function
//! of (data, k, iteration cap, RNG state). Ties in distance always go to the lowest
//! center index.

use common::descriptor::Descriptor;
use rand::Rng;

/// The result of [`k_majority`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Clustering {
    /// The cluster centers; every center has at least one member.
    pub centers: Vec<Descriptor>,
    /// For each input descriptor, the index of its center in `centers`. Each
    /// descriptor is assigned to its nearest center (ties to the lowest index), so
    /// the partition agrees with a greedy nearest-center descent.
    pub assignment: Vec<usize>,
    /// Number of center updates performed.
    pub iterations: usize,
    /// Whether the assignments stopped changing before the iteration cap.
    pub converged: bool,
}

/// Bitwise majority of `members`: bit `i` is set iff strictly more than half of
/// the members have bit `i` set (a tie gives 0). An empty set gives the zero
/// descriptor.
pub fn majority<'a, I>(members: I) -> Descriptor
where
    I: IntoIterator<Item = &'a Descriptor>,
{
    let mut counts = [0u32; Descriptor::BITS];
    let mut n = 0u32;
    for d in members {
        n += 1;
        for (w, &word) in d.0.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let b = bits.trailing_zeros() as usize;
                counts[w * 64 + b] += 1;
                bits &= bits - 1;
            }
        }
    }
    let mut out = Descriptor::default();
    for (i, &c) in counts.iter().enumerate() {
        if 2 * u64::from(c) > u64::from(n) {
            out.flip(i);
        }
    }
    out
}

/// Index of the center nearest to `d` (ties to the lowest index) and its distance;
/// `None` if there are no centers.
pub fn nearest(d: &Descriptor, centers: &[Descriptor]) -> Option<(usize, u32)> {
    let mut best: Option<(usize, u32)> = None;
    for (i, c) in centers.iter().enumerate() {
        let dist = d.distance(c);
        if best.is_none_or(|(_, b)| dist < b) {
            best = Some((i, dist));
        }
    }
    best
}

/// k-means++ seeding: the first seed is drawn uniformly, every further seed with
/// probability proportional to its squared Hamming distance to the nearest seed
/// chosen so far. Sampling uses exact integer weights, so it is deterministic for a
/// given RNG state.
///
/// Returns at most `k` seeds, all distinct: fewer when `data` has fewer than `k`
/// distinct descriptors. Empty `data` or `k == 0` gives no seeds.
pub fn seed_kmeans_pp<R: Rng + ?Sized>(
    data: &[Descriptor],
    k: usize,
    rng: &mut R,
) -> Vec<Descriptor> {
    let mut seeds = Vec::with_capacity(k.min(data.len()));
    if data.is_empty() || k == 0 {
        return seeds;
    }
    let first = data[rng.random_range(0..data.len())];
    seeds.push(first);
    let mut d2: Vec<u64> = data
        .iter()
        .map(|d| u64::from(d.distance(&first)).pow(2))
        .collect();
    while seeds.len() < k {
        let total: u64 = d2.iter().sum();
        if total == 0 {
            break; // every descriptor coincides with a seed
        }
        let r = rng.random_range(0..total);
        let mut acc = 0u64;
        // The first index whose cumulative weight exceeds r has a positive weight,
        // so it is never an existing seed.
        let pick = d2
            .iter()
            .position(|&w| {
                acc += w;
                acc > r
            })
            .unwrap_or(data.len() - 1);
        let seed = data[pick];
        seeds.push(seed);
        for (w, d) in d2.iter_mut().zip(data) {
            let dist = u64::from(d.distance(&seed)).pow(2);
            if dist < *w {
                *w = dist;
            }
        }
    }
    seeds
}

/// Assigns every descriptor to its nearest center (ties to the lowest index).
fn assign_all(data: &[Descriptor], centers: &[Descriptor]) -> Vec<usize> {
    data.iter()
        .map(|d| nearest(d, centers).map_or(0, |(i, _)| i))
        .collect()
}

/// Recomputes each center as the majority of its members; a center without
/// members keeps its previous value.
fn update_centers(data: &[Descriptor], assignment: &[usize], centers: &mut [Descriptor]) {
    let mut members: Vec<Vec<Descriptor>> = vec![Vec::new(); centers.len()];
    for (d, &a) in data.iter().zip(assignment) {
        if let Some(m) = members.get_mut(a) {
            m.push(*d);
        }
    }
    for (c, m) in centers.iter_mut().zip(&members) {
        if !m.is_empty() {
            *c = majority(m);
        }
    }
}

/// k-majority clustering of `data` into at most `k` clusters, seeded by
/// [`seed_kmeans_pp`]: alternate center updates (bitwise majority of the members)
/// and nearest-center assignment until the assignment stops changing or
/// `max_iterations` updates were made. Empty clusters are dropped, so the result
/// may have fewer than `k` centers (always at least one if `data` is non-empty).
/// A `k` of 0 counts as 1.
pub fn k_majority<R: Rng + ?Sized>(
    data: &[Descriptor],
    k: usize,
    max_iterations: usize,
    rng: &mut R,
) -> Clustering {
    let mut centers = seed_kmeans_pp(data, k.max(1), rng);
    let mut assignment = assign_all(data, &centers);
    let mut iterations = 0;
    let mut converged = false;
    while iterations < max_iterations {
        iterations += 1;
        update_centers(data, &assignment, &mut centers);
        let next = assign_all(data, &centers);
        if next == assignment {
            converged = true;
            break;
        }
        assignment = next;
    }
    // Drop empty clusters and renumber the rest in their original order.
    let mut used = vec![false; centers.len()];
    for &a in &assignment {
        used[a] = true;
    }
    let mut remap = vec![usize::MAX; centers.len()];
    let mut kept = Vec::with_capacity(centers.len());
    for (i, c) in centers.iter().enumerate() {
        if used[i] {
            remap[i] = kept.len();
            kept.push(*c);
        }
    }
    for a in &mut assignment {
        *a = remap[*a];
    }
    Clustering {
        centers: kept,
        assignment,
        iterations,
        converged,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn random_descriptors(n: usize, seed: u64) -> Vec<Descriptor> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
            .collect()
    }

    #[test]
    fn majority_is_the_bitwise_majority() {
        let data = random_descriptors(7, 3);
        let m = majority(&data);
        for i in 0..Descriptor::BITS {
            let ones = data.iter().filter(|d| d.bit(i)).count();
            assert_eq!(m.bit(i), ones * 2 > data.len(), "bit {i}");
        }
        // Even count: ties go to 0.
        let a = Descriptor([u64::MAX; 4]);
        let b = Descriptor([0; 4]);
        assert_eq!(majority(&[a, b]), Descriptor([0; 4]));
        assert_eq!(majority(&[a, a, b]), a);
        assert_eq!(majority(&[]), Descriptor::default());
    }

    #[test]
    fn single_cluster_center_is_the_majority() {
        let data = random_descriptors(51, 4);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let c = k_majority(&data, 1, 10, &mut rng);
        assert_eq!(c.centers, vec![majority(&data)]);
        assert!(c.converged);
    }

    #[test]
    fn converged_centers_are_majorities_of_their_members() {
        let data = random_descriptors(500, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let c = k_majority(&data, 6, 100, &mut rng);
        assert!(c.converged);
        for (ci, center) in c.centers.iter().enumerate() {
            let members: Vec<_> = data
                .iter()
                .zip(&c.assignment)
                .filter(|(_, &a)| a == ci)
                .map(|(d, _)| *d)
                .collect();
            assert!(!members.is_empty());
            assert_eq!(*center, majority(&members));
        }
        for (d, &a) in data.iter().zip(&c.assignment) {
            assert_eq!(nearest(d, &c.centers).map(|x| x.0), Some(a));
        }
    }

    #[test]
    fn seeding_is_deterministic_per_seed() {
        let data = random_descriptors(300, 6);
        let s1 = seed_kmeans_pp(&data, 10, &mut ChaCha8Rng::seed_from_u64(9));
        let s2 = seed_kmeans_pp(&data, 10, &mut ChaCha8Rng::seed_from_u64(9));
        let s3 = seed_kmeans_pp(&data, 10, &mut ChaCha8Rng::seed_from_u64(10));
        assert_eq!(s1, s2);
        assert_ne!(s1, s3);
        assert_eq!(s1.len(), 10);
        for (i, a) in s1.iter().enumerate() {
            assert!(data.contains(a));
            assert!(s1[..i].iter().all(|b| b != a), "seeds are distinct");
        }
    }

    #[test]
    fn seeding_prefers_far_points() {
        // 99 copies of one descriptor and one far away: the second seed must be the
        // other one whichever comes first.
        let a = Descriptor([0; 4]);
        let b = Descriptor([u64::MAX; 4]);
        let mut data = vec![a; 99];
        data.push(b);
        for seed in 0..20 {
            let s = seed_kmeans_pp(&data, 2, &mut ChaCha8Rng::seed_from_u64(seed));
            assert_eq!(s.len(), 2);
            assert!(s.contains(&a) && s.contains(&b));
        }
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let empty = k_majority(&[], 4, 10, &mut rng);
        assert!(empty.centers.is_empty() && empty.assignment.is_empty());

        let few = random_descriptors(3, 1);
        let c = k_majority(&few, 0, 10, &mut rng);
        assert_eq!(c.centers, vec![majority(&few)]);

        let c = k_majority(&few, 10, 10, &mut rng);
        assert_eq!(c.centers.len(), 3);

        let dup = vec![Descriptor([7, 7, 7, 7]); 40];
        let c = k_majority(&dup, 5, 10, &mut rng);
        assert_eq!(c.centers, vec![dup[0]]);
        assert!(c.assignment.iter().all(|&a| a == 0));

        let mut two = vec![Descriptor([1, 0, 0, 0]); 20];
        two.extend(vec![Descriptor([0, 0, 0, 1]); 20]);
        let c = k_majority(&two, 8, 0, &mut rng);
        assert_eq!(c.centers.len(), 2);
    }
}
