//! One CI-EKF update per frame (thesis Eqs. 5.14-5.17) from every cooperative
//! row of the frame: common VIO features, peers' measurements of our SLAM
//! features and SLAM constraints.
//!
//! Each CI update inflates our whole covariance by `1/ω_i`, and that inflation
//! compounds in the directions no measurement constrains (global position and
//! yaw); stacking the frame's cooperative rows into one update pays it once.
//!
//! A participant is a part of one peer window: its camera poses (weight
//! `ci_peer_weight`) or some of its SLAM landmarks (weight
//! `constraint_peer_weight`). Peers send only the landmarks' marginals, whose
//! cross-correlations are unknown too: `k` landmarks of one window are bounded
//! together by CI with equal weights, `Diag(k P_1, ..., k P_k)`.

use super::ci_split;
use super::feature_system::Columns;
use super::linalg::compress_in_place;
use super::peer_window::{FrameLink, PeerWindow};
use super::state::{wrap_yaw, State, StateError, Var};
use super::updater_ci::{self, CiOutcome, CiWeights, PeerTerm};
use common::estimator_options::CooperationOptions;
use nalgebra::{DMatrix, DVector};

/// Which part of a peer window a row block involves.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Part {
    /// The camera poses of window `w` (index into the participants).
    Poses(usize),
    /// The SLAM landmarks of window `w`.
    Landmarks(usize),
}

impl Part {
    /// The participant window it belongs to.
    pub fn window(self) -> usize {
        match self {
            Part::Poses(w) | Part::Landmarks(w) => w,
        }
    }

    /// Columns of item `item`: a pose (6) or the intrinsics (8) of a window, a
    /// landmark (3).
    pub fn item_size(self, item: usize, participants: &[PeerWindow]) -> usize {
        match self {
            Part::Poses(w) => participants.get(w).map_or(6, |p| p.item_size(item)),
            Part::Landmarks(_) => 3,
        }
    }

    /// Column offset of each of `items`, and the total.
    fn layout(self, items: &[usize], participants: &[PeerWindow]) -> (Vec<usize>, usize) {
        let mut offsets = Vec::with_capacity(items.len());
        let mut total = 0;
        for i in items {
            offsets.push(total);
            total += self.item_size(*i, participants);
        }
        (offsets, total)
    }
}

/// A block's Jacobian with respect to one participant: over `items` (pose or
/// landmark indices of the window, sorted), `m x width·items`.
#[derive(Clone, Debug, PartialEq)]
pub struct PeerRows {
    /// The participant.
    pub part: Part,
    /// Its items, sorted.
    pub items: Vec<usize>,
    /// The Jacobian.
    pub h: DMatrix<f64>,
}

/// A block of whitened rows (unit noise) relating our variables `vars` to
/// participants: `r = H δx + Σ H_o δx_o + n`.
#[derive(Clone, Debug, PartialEq)]
pub struct CiRows {
    /// Our variables, the columns of `h` in order.
    pub vars: Vec<Var>,
    /// Our Jacobian.
    pub h: DMatrix<f64>,
    /// Residuals.
    pub res: DVector<f64>,
    /// The participants' Jacobians.
    pub peers: Vec<PeerRows>,
}

impl CiRows {
    /// Whether the block involves participant window `w`.
    pub fn involves(&self, w: usize) -> bool {
        self.peers.iter().any(|p| p.part.window() == w)
    }
}

/// The participant windows `rows` involve, sorted.
pub fn windows(rows: &[CiRows]) -> Vec<usize> {
    let mut out: Vec<usize> = rows
        .iter()
        .flat_map(|r| r.peers.iter().map(|p| p.part.window()))
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// The columns a block's Jacobian `h_p` over `items` of participant `part`
/// gives our peer frame, when the window was taken into our frame through a
/// frame our state holds: `h_p G` (m x 4), `G` the items' rows of the
/// window's Jacobian w.r.t. the frame, with the window's link to the frame.
/// `None` for any other window.
pub fn frame_columns<'w>(
    part: Part,
    items: &[usize],
    h_p: &DMatrix<f64>,
    participants: &'w [PeerWindow],
) -> Option<(&'w FrameLink, DMatrix<f64>)> {
    let w = participants.get(part.window())?;
    let link = w.frame.as_ref()?;
    let (offsets, total) = part.layout(items, participants);
    if h_p.ncols() != total {
        return None;
    }
    let mut out = DMatrix::zeros(h_p.nrows(), 4);
    for (item, c) in items.iter().zip(offsets) {
        let size = part.item_size(*item, participants);
        let cols = h_p.columns(c, size);
        match part {
            // A pose's 6 rows of `G` (the intrinsics do not move with the frame).
            Part::Poses(_) if *item < w.poses.len() => {
                out += cols * link.poses.rows(6 * item, 6);
            }
            Part::Poses(_) => {}
            Part::Landmarks(_) => out += cols * link.landmarks.get(*item)?,
        }
    }
    Some((link.as_ref(), out))
}

/// Adds to our block `(vars, h)` the columns of the peer frames its
/// participants depend on ([`frame_columns`]), so that gating and the CI-EKF
/// update see the frame's uncertainty through our covariance, and the update
/// corrects the frame. A window taken into our frame at a mean the state has
/// since moved from (this frame's own updates came after the evidence) has
/// its residuals moved to the current mean, to first order: `r −= H_a δa`.
pub fn add_frame_columns<'a>(
    state: &State,
    vars: &mut Vec<Var>,
    h: &mut DMatrix<f64>,
    res: &mut DVector<f64>,
    peers: impl IntoIterator<Item = (Part, &'a [usize], &'a DMatrix<f64>)>,
    participants: &[PeerWindow],
) {
    for (part, items, h_p) in peers {
        let Some((link, cols)) = frame_columns(part, items, h_p, participants) else {
            continue;
        };
        let var = link.var;
        if let Var::PeerFrame { peer, epoch } = var {
            if let Some(now) = state.peer_frames.get(&(peer, epoch)) {
                let d = now.t_m - link.at.t_m;
                let moved = DVector::from_column_slice(&[
                    wrap_yaw(now.yaw_rad - link.at.yaw_rad),
                    d.x,
                    d.y,
                    d.z,
                ]);
                if moved.iter().any(|v| *v != 0.0) {
                    *res -= &cols * moved;
                }
            }
        }
        let at = match vars.iter().position(|v| *v == var) {
            Some(i) => vars[..i].iter().map(|v| v.size()).sum(),
            None => {
                let c = h.ncols();
                let m = h.nrows();
                let old = std::mem::replace(h, DMatrix::zeros(m, c + 4));
                h.columns_mut(0, c).copy_from(&old);
                vars.push(var);
                c
            }
        };
        let mut dst = h.columns_mut(at, 4);
        dst += cols;
    }
}

/// [`add_frame_columns`] for a block whose participants' Jacobians are its own.
pub fn add_block_frame_columns(state: &State, rows: &mut CiRows, participants: &[PeerWindow]) {
    let mut vars = std::mem::take(&mut rows.vars);
    let mut h = std::mem::replace(&mut rows.h, DMatrix::zeros(0, 0));
    add_frame_columns(
        state,
        &mut vars,
        &mut h,
        &mut rows.res,
        rows.peers
            .iter()
            .map(|p| (p.part, p.items.as_slice(), &p.h)),
        participants,
    );
    rows.vars = vars;
    rows.h = h;
}

/// Moves the residuals of blocks linearized before an update that applied `dx`
/// to first order: `r ← r − H δx`.
pub fn correct_residuals(rows: &mut [CiRows], state: &State, dx: &DVector<f64>) {
    for b in rows {
        let mut d = DVector::zeros(b.h.ncols());
        let mut c = 0;
        for v in &b.vars {
            if let Some(o) = state.offset(*v) {
                d.rows_mut(c, v.size()).copy_from(&dx.rows(o, v.size()));
            }
            c += v.size();
        }
        b.res -= &b.h * d;
    }
}

/// The covariance of `items` of participant `part`.
fn part_covariance(part: Part, items: &[usize], participants: &[PeerWindow]) -> DMatrix<f64> {
    match part {
        Part::Poses(w) => participants[w].sub_covariance(items),
        Part::Landmarks(w) => {
            let k = items.len();
            let mut out = DMatrix::identity(3 * k, 3 * k);
            for (a, &j) in items.iter().enumerate() {
                if let Some(lm) = participants[w].landmarks.get(j) {
                    out.view_mut((3 * a, 3 * a), (3, 3))
                        .copy_from(&(lm.cov * k as f64));
                }
            }
            out
        }
    }
}

/// `B` of the part `B Bᵀ` of a peer window's covariance `cov` (over `items`)
/// that its intrinsics hold given its poses (`ci_split::peer_intrinsics_factor`),
/// when the update involves them; `None` otherwise.
fn peer_intrinsics_part(
    part: Part,
    items: &[usize],
    cov: &DMatrix<f64>,
    participants: &[PeerWindow],
) -> Option<DMatrix<f64>> {
    let Part::Poses(w) = part else {
        return None;
    };
    let intrinsics = participants.get(w)?.intrinsics_item()?;
    let at = items.iter().position(|i| *i == intrinsics)?;
    let (offsets, _) = part.layout(items, participants);
    ci_split::peer_intrinsics_factor(cov, offsets[at])
}

/// `rows` stacked over one set of columns: ours (`cols`) and each
/// participant's items.
struct Stacked {
    cols: Columns,
    h: DMatrix<f64>,
    parts: Vec<(Part, Vec<usize>)>,
    h_parts: Vec<DMatrix<f64>>,
    res: DVector<f64>,
}

/// Stacks `rows`; `None` when there are none.
fn stack(rows: &[&CiRows], participants: &[PeerWindow]) -> Option<Stacked> {
    let m: usize = rows.iter().map(|r| r.res.len()).sum();
    if m == 0 {
        return None;
    }
    let mut vars: Vec<Var> = Vec::new();
    let mut parts: Vec<(Part, Vec<usize>)> = Vec::new();
    for r in rows {
        for v in &r.vars {
            if !vars.contains(v) {
                vars.push(*v);
            }
        }
        for p in &r.peers {
            match parts.iter_mut().find(|(q, _)| *q == p.part) {
                Some((_, items)) => items.extend(&p.items),
                None => parts.push((p.part, p.items.clone())),
            }
        }
    }
    parts.sort_by_key(|(p, _)| *p);
    for (_, items) in parts.iter_mut() {
        items.sort_unstable();
        items.dedup();
    }
    let cols = Columns::of(vars);
    let mut h = DMatrix::zeros(m, cols.dim);
    let mut res = DVector::zeros(m);
    let layouts: Vec<(Vec<usize>, usize)> = parts
        .iter()
        .map(|(p, items)| p.layout(items, participants))
        .collect();
    let mut h_parts: Vec<DMatrix<f64>> = layouts
        .iter()
        .map(|(_, total)| DMatrix::zeros(m, *total))
        .collect();
    let mut r0 = 0;
    for r in rows {
        let k = r.res.len();
        let local = Columns::of(r.vars.clone());
        for v in &r.vars {
            if let (Some(s), Some(d)) = (local.col(*v), cols.col(*v)) {
                let mut dst = h.view_mut((r0, d), (k, v.size()));
                dst += r.h.view((0, s), (k, v.size()));
            }
        }
        res.rows_mut(r0, k).copy_from(&r.res);
        for p in &r.peers {
            let Some(j) = parts.iter().position(|(q, _)| *q == p.part) else {
                continue;
            };
            let (src, _) = p.part.layout(&p.items, participants);
            for (a, item) in p.items.iter().enumerate() {
                let w = p.part.item_size(*item, participants);
                if let Ok(g) = parts[j].1.binary_search(item) {
                    let dst = layouts[j].0[g];
                    h_parts[j]
                        .view_mut((r0, dst), (k, w))
                        .copy_from(&p.h.view((0, src[a]), (k, w)));
                }
            }
        }
        r0 += k;
    }
    Some(Stacked {
        cols,
        h,
        parts,
        h_parts,
        res,
    })
}

/// `rᵀ S⁻¹ r` and the rows of `rows` stacked, with `S` the innovation
/// covariance the blocks' own gates take: robots not correlated (every CI
/// weight 1). The blocks are gated one by one; stacked, the rows that share
/// a peer's pose see its error whole.
pub fn independent_mahalanobis(
    state: &State,
    rows: &[&CiRows],
    participants: &[PeerWindow],
) -> Option<(f64, usize)> {
    let st = stack(rows, participants)?;
    let s = independent_covariance(state, &st, participants)?;
    let chol = s.cholesky()?;
    Some((st.res.dot(&chol.solve(&st.res)), st.res.len()))
}

/// The innovation covariance `S` of [`independent_mahalanobis`], in the
/// cheaper of two forms for what is done with it.
#[derive(Clone, Debug)]
pub enum Innovation {
    /// `S` itself: no more rows than the variables' dimensions.
    Covariance(DMatrix<f64>),
    /// `V` with `S = I + V Vᵀ` (the rows are whitened): `V = [H L, H_p L_p,
    /// ...]`, `L` a square root of each covariance, has one column per
    /// variable dimension, far fewer than the rows of a window whose peers
    /// saw our features from every pose (stop 90: 400-1000 rows over
    /// 200-400 columns).
    Factor(DMatrix<f64>),
}

/// [`Innovation`] of `rows` stacked in their order, and the residual. A
/// subset of the blocks has the submatrix of `S`, or the subset of `V`'s
/// rows (each term is `H C Hᵀ`, and a row's Jacobian is zero off its own
/// variables).
pub fn independent_innovation(
    state: &State,
    rows: &[&CiRows],
    participants: &[PeerWindow],
) -> Option<(Innovation, DVector<f64>)> {
    independent_innovation_as(state, rows, participants, |m, q| m > q)
}

/// [`independent_innovation`] as a factor when `factor(m, q)` says so, for
/// `m` rows over `q` variable dimensions.
pub(crate) fn independent_innovation_as(
    state: &State,
    rows: &[&CiRows],
    participants: &[PeerWindow],
    factor: impl Fn(usize, usize) -> bool,
) -> Option<(Innovation, DVector<f64>)> {
    let st = stack(rows, participants)?;
    let q = st.cols.dim + st.h_parts.iter().map(|h| h.ncols()).sum::<usize>();
    let form = if factor(st.res.len(), q) {
        Innovation::Factor(independent_factor(state, &st, participants)?)
    } else {
        Innovation::Covariance(independent_covariance(state, &st, participants)?)
    };
    Some((form, st.res))
}

fn independent_covariance(
    state: &State,
    st: &Stacked,
    participants: &[PeerWindow],
) -> Option<DMatrix<f64>> {
    let m = st.res.len();
    let mut s = state.covariance().projected(&st.cols.vars, &st.h).ok()? + DMatrix::identity(m, m);
    for ((p, items), hp) in st.parts.iter().zip(&st.h_parts) {
        s += hp * part_covariance(*p, items, participants) * hp.transpose();
    }
    Some(s)
}

fn independent_factor(
    state: &State,
    st: &Stacked,
    participants: &[PeerWindow],
) -> Option<DMatrix<f64>> {
    let ours = state.covariance().gather(&st.cols.vars).ok()?;
    let mut factors = vec![&st.h * square_root(ours)?];
    for ((p, items), hp) in st.parts.iter().zip(&st.h_parts) {
        factors.push(hp * square_root(part_covariance(*p, items, participants))?);
    }
    let q = factors.iter().map(|f| f.ncols()).sum();
    let mut v = DMatrix::zeros(st.res.len(), q);
    let mut c0 = 0;
    for f in &factors {
        v.columns_mut(c0, f.ncols()).copy_from(f);
        c0 += f.ncols();
    }
    Some(v)
}

/// `L` with `L Lᵀ = c`: the Cholesky factor, or from the eigenvalues (those
/// below zero by rounding taken as zero) when `c` is only semidefinite.
fn square_root(c: DMatrix<f64>) -> Option<DMatrix<f64>> {
    if c.iter().any(|x| !x.is_finite()) {
        return None;
    }
    if let Some(chol) = c.clone().cholesky() {
        return Some(chol.l());
    }
    let eig = c.symmetric_eigen();
    let roots = eig.eigenvalues.map(|l| l.max(0.0).sqrt());
    Some(eig.eigenvectors * DMatrix::from_diagonal(&roots))
}

/// Stacks `rows` and applies one CI-EKF update. `Ok(None)` when there is
/// nothing to do.
pub fn update(
    state: &mut State,
    rows: &[CiRows],
    participants: &[PeerWindow],
    opts: &CooperationOptions,
) -> Result<Option<CiOutcome>, StateError> {
    let Some(Stacked {
        cols,
        h,
        parts,
        h_parts,
        res,
    }) = stack(&rows.iter().collect::<Vec<_>>(), participants)
    else {
        return Ok(None);
    };
    let (h, h_parts, res) = compress_joint(h, h_parts, res);
    // Whitened rows; with `split_calibration`, plus the peers' intrinsics'
    // part that is not inflated (`ci_split::peer_intrinsics_factor`).
    let mut noise = DMatrix::identity(res.len(), res.len());
    let terms: Vec<PeerTerm> = parts
        .iter()
        .zip(h_parts)
        .map(|((p, items), hp)| {
            let mut cov = part_covariance(*p, items, participants);
            if opts.split_calibration {
                if let Some(b) = peer_intrinsics_part(*p, items, &cov, participants) {
                    let hb = &hp * &b;
                    cov -= &b * b.transpose();
                    noise += &hb * hb.transpose();
                }
            }
            PeerTerm {
                h: hp,
                cov,
                weight: Some(match p {
                    Part::Poses(_) => opts.ci_peer_weight,
                    Part::Landmarks(_) => opts.constraint_peer_weight,
                }),
            }
        })
        .collect();
    let weights = weights_of(opts);
    // Split CI only when no participant sees our frame's yaw and translation:
    // each came into our frame through a peer frame our state holds.
    let through_held_frames = !parts.is_empty()
        && parts.iter().all(|(p, _)| {
            participants
                .get(p.window())
                .is_some_and(|pw| pw.frame.is_some())
        });
    let unobserved = split_factor(state, opts, through_held_frames);
    updater_ci::update(
        state,
        &cols.vars,
        &h,
        &res,
        &noise,
        &terms,
        &weights,
        unobserved.as_ref(),
    )
    .map(Some)
}

/// The part of our covariance CI does not inflate (split CI, `ci_split`): our
/// world's yaw and translation when every participant comes through a frame
/// our state holds (`split_unobservable`), our calibration
/// (`split_calibration`), both conditioned on the rest. `None`: all is
/// inflated.
fn split_factor(
    state: &State,
    opts: &CooperationOptions,
    through_held_frames: bool,
) -> Option<DMatrix<f64>> {
    let mut blocks: Vec<DMatrix<f64>> = Vec::new();
    if opts.split_unobservable && through_held_frames {
        let cols = Columns::of(state.vars().collect());
        blocks.push(super::observability::unobservable_directions(
            &cols,
            &state.means,
        ));
    }
    if opts.split_calibration {
        blocks.extend(ci_split::calibration_directions(state));
    }
    let k: usize = blocks.iter().map(|b| b.ncols()).sum();
    if k == 0 {
        return None;
    }
    let mut n = DMatrix::zeros(state.dim(), k);
    let mut c = 0;
    for b in &blocks {
        n.columns_mut(c, b.ncols()).copy_from(b);
        c += b.ncols();
    }
    ci_split::conditional_factor(state, &n)
}

/// How the options choose the CI weights.
pub fn weights_of(opts: &CooperationOptions) -> CiWeights {
    match opts.ci_weighting {
        common::estimator_options::CiWeighting::FixedPeer => {
            CiWeights::FixedPeer(opts.ci_peer_weight)
        }
        common::estimator_options::CiWeighting::FixedOwn => CiWeights::FixedOwn(opts.ci_own_weight),
        common::estimator_options::CiWeighting::MinTrace => CiWeights::MinTrace,
        common::estimator_options::CiWeighting::MinPoseTrace => CiWeights::MinPoseTrace,
        common::estimator_options::CiWeighting::MinDeterminant => CiWeights::MinDeterminant,
        common::estimator_options::CiWeighting::MinPoseFeaturesDeterminant => {
            CiWeights::MinPoseFeaturesDeterminant
        }
    }
}

/// Compresses `[H | H_1 | ... | H_L], r` when it has more rows than columns
/// (white noise stays white under the orthogonal transform).
fn compress_joint(
    h: DMatrix<f64>,
    h_parts: Vec<DMatrix<f64>>,
    res: DVector<f64>,
) -> (DMatrix<f64>, Vec<DMatrix<f64>>, DVector<f64>) {
    let m = res.len();
    let widths: Vec<usize> = std::iter::once(h.ncols())
        .chain(h_parts.iter().map(|p| p.ncols()))
        .collect();
    let total: usize = widths.iter().sum();
    if m <= total {
        return (h, h_parts, res);
    }
    let mut all = DMatrix::zeros(m, total);
    let mut c0 = 0;
    for part in std::iter::once(&h).chain(h_parts.iter()) {
        all.view_mut((0, c0), (m, part.ncols())).copy_from(part);
        c0 += part.ncols();
    }
    let mut res = res;
    compress_in_place(&mut all, &mut res);
    let mut split = Vec::with_capacity(widths.len());
    let mut c0 = 0;
    for w in widths {
        split.push(all.columns(c0, w).into_owned());
        c0 += w;
    }
    let mut it = split.into_iter();
    let h = it.next().unwrap_or_else(|| DMatrix::zeros(res.len(), 0));
    (h, it.collect(), res)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_square_root_of_a_semidefinite_covariance_gives_it_back() {
        let a = DMatrix::from_fn(5, 3, |i, j| ((i * 3 + j) as f64).sin());
        // Positive definite: the Cholesky factor.
        let pd = &a * a.transpose() + DMatrix::identity(5, 5);
        let l = square_root(pd.clone()).unwrap();
        assert!((&l * l.transpose() - &pd).norm() < 1e-12);
        // Rank 3 of 5, its zero eigenvalues rounded below zero: no Cholesky
        // factor, the eigenvalues' root.
        let psd = &a * a.transpose() - DMatrix::identity(5, 5) * 1e-13;
        assert!(psd.clone().cholesky().is_none());
        let l = square_root(psd.clone()).unwrap();
        assert!((&l * l.transpose() - &psd).norm() < 1e-10);
        assert!(square_root(DMatrix::from_element(2, 2, f64::NAN)).is_none());
    }
}
