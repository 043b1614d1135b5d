//! The projected codec's unit tests: coding, the continuation operator, its chains and records.

use super::*;
use crate::core::decode;
use crate::core::operator::{Chain, Operator, Step};

/// A small rough grid: a smooth slope plus a hashed roughness.
pub(super) fn grid(w: usize, h: usize) -> Vec<f64> {
    (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            let noise = (i as u32).wrapping_mul(2_654_435_761) as f64 / u32::MAX as f64;
            3.0 * x + 2.0 * y + 10.0 * noise
        })
        .collect()
}

pub(super) fn header(w: usize, h: usize, g: &[f64]) -> ProjectedHeader {
    let (lo, hi) = g
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    ProjectedHeader {
        samples: [w as u32, h as u32],
        levels: levels_for(w, h),
        step: 1.0,
        growth: 1.0,
        quantum: 0.0,
        value_min: lo,
        value_span: hi - lo,
        roughness: fit_roughness(g, w, h),
        max_error: 0.5,
        order: pyramid::Order::QuincunxTwoRate,
    }
}

/// The lanes of `run_chains` answer as one chain at a time does, bit for bit: each stepped
/// by `step` while it has steps left and its cell's residual bound times its contrast
/// product is over the tolerance, then ended on S.
#[test]
fn chains_in_lanes_answer_as_one_at_a_time() {
    use crate::core::decode::{position_quantum, to_frame};
    use crate::core::operator::active;
    let (w, h) = (41, 29);
    let g = grid(w, h);
    let op = ProjectedOperator::new(&header(w, h, &g), &g).expect("operator");
    assert!(op.ends_on_samples());
    let (lo, hi) = op.invariant_interval();
    let (seed, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
    let quantum = position_quantum(&op.frame());
    // 1,003 points (a last batch of three), some past the frame's edges.
    let pts: Vec<[f32; 2]> = (0..1003)
        .map(|k| {
            let t = k as f32;
            [
                (t * 0.618_034).fract() * 1.1 - 0.05,
                (t * 0.414_214).fract(),
            ]
        })
        .collect();
    for (iterations, tol) in [(3, 0.0), (40, 1e-3), (40, 2e-2), (0, 0.0)] {
        let lanes = decode::points(&op, &pts, iterations, tol);
        for (k, p) in pts.iter().enumerate() {
            let mut c = Chain::start([
                to_frame(p[0], op.valid()[0], quantum),
                to_frame(p[1], op.valid()[1], quantum),
            ]);
            while c.taken < iterations && active(c.acc_s, op.residual_at(c.q), tol) {
                let st = op.step(c.q);
                c.taken += 1;
                c.acc_g += c.acc_s * st.offset;
                c.acc_s *= st.contrast;
                c.q = st.next;
            }
            op.end_chain(&mut c);
            assert_eq!(
                lanes[k],
                c.finish(seed, half),
                "point {k}, {iterations} steps"
            );
        }
    }
}

/// The records built from the half lattices are the bits the direct tensor-product
/// evaluation gives, on rough and smooth grids of odd and even sizes and the smallest axes.
/// (Unit tests read no files: the layout rule keeps `codecs` from importing `io`.)
#[test]
fn records_from_half_lattices_are_the_direct_evaluations_bit_for_bit() {
    let smooth = |w: usize, h: usize| -> Vec<f64> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                1234.5 * (0.3 * x).sin() * (0.21 * y).cos() - 17.25 * x
            })
            .collect()
    };
    let mut cases: Vec<(usize, usize, Vec<f64>)> = [(61, 40), (64, 33), (5, 4), (4, 7), (2, 3)]
        .iter()
        .flat_map(|&(w, h)| [(w, h, grid(w, h)), (w, h, smooth(w, h))])
        .collect();
    cases.push((17, 12, grid(17, 12)));
    for (w, h, g) in cases {
        // A roughness of its own, so that the even lattice's term is weighed everywhere.
        let hd = ProjectedHeader {
            roughness: 0.6,
            ..header(w, h, &g)
        };
        let op = ProjectedOperator::new(&hd, &g).expect("operator");
        assert!(op.rho > 0.0 || w < 4 || h < 4);
        for (k, rec) in op.records.iter().enumerate() {
            let (i, j) = (k % (w - 1), k / (w - 1));
            for (n, &v) in rec.iter().enumerate() {
                let direct = op.half_point(i, j, n % 3, n / 3);
                assert_eq!(
                    v.to_bits(),
                    direct.to_bits(),
                    "{w}x{h} cell ({i}, {j}) point {n}"
                );
            }
        }
    }
}

#[test]
fn the_continuation_passes_through_every_sample_and_its_pieces_agree() {
    for (w, h) in [(17, 12), (16, 9), (4, 4), (2, 5)] {
        let g = grid(w, h);
        let hd = header(w, h, &g);
        let op = ProjectedOperator::new(&hd, &g).expect("operator");
        let pts: Vec<[f32; 2]> = (0..w * h)
            .map(|i| {
                [
                    ((i % w) as f32 + 0.5) / w as f32,
                    ((i / w) as f32 + 0.5) / h as f32,
                ]
            })
            .collect();
        for (k, pv) in decode::points(&op, &pts, 400, 0.0).iter().enumerate() {
            let want = op.samples()[k];
            assert!(
                (pv.value - want).abs() < 1e-4,
                "{w}x{h} sample {k}: {} against {want}",
                pv.value
            );
        }
        // The GPU's flattening steps as `step` does, seeded by a constant.
        crate::core::pieces::tests::agree(&Stepwise(&op), "projected");
        // And goes to a device as a lattice: the quarter cells' offsets (16 bytes each
        // against a piece's 80 and its lookup entry's 4), a map a column and a row.
        let table = crate::core::pieces::Flatten::pieces(&op);
        let lattice = table.lattice().expect("the quarter cells are a lattice");
        // Built directly, the same lattice, with where chains end: the samples and each
        // cell's residual bound, when chains end on them.
        let crate::core::pieces::Flat::Lattice(direct) = crate::core::pieces::Flatten::flat(&op)
        else {
            panic!("the projected codec flattens to a lattice");
        };
        let ends = direct.ends.clone();
        let direct = crate::core::pieces::Lattice {
            ends: None,
            ..direct
        };
        let [lx, ly] = table.lut_size.map(|n| n as usize);
        // Its offsets in blocks, a cell's record shared by its four quarters, are the
        // table's coefficients cell by cell.
        use crate::core::pieces::Offsets;
        let Offsets::Blocks(blocks) = &direct.offsets else {
            panic!("the quarter cells' offsets go in blocks");
        };
        assert_eq!(blocks.len() * 4, lx * ly);
        let cells = (0..lx * ly)
            .map(|k| direct.offsets.of(k % lx, k / lx, lx))
            .collect();
        assert_eq!(
            crate::core::pieces::Lattice {
                offsets: Offsets::Cells(cells),
                ..direct.clone()
            },
            lattice
        );
        assert_eq!(ends.is_some(), op.ends_on_samples());
        if let Some(e) = ends {
            assert_eq!(e.samples.as_slice(), op.samples());
            assert_eq!(e.residual.len(), (w - 1) * (h - 1));
            assert_eq!(e.residual[w], op.residual_of(w % (w - 1), w / (w - 1)));
        }
        // And from an operator holding no records (a chunk's), which builds them all for
        // its lattice by bands rather than holding them: the same lattice.
        let lean = ProjectedOperator::samples_only(&hd, &g).expect("operator");
        let crate::core::pieces::Flat::Lattice(lean) = crate::core::pieces::Flatten::flat(&lean)
        else {
            panic!("the projected codec flattens to a lattice");
        };
        assert_eq!(crate::core::pieces::Lattice { ends: None, ..lean }, direct);
        assert_eq!((direct.columns.len(), direct.rows.len()), (lx, ly));
        assert_eq!(table.device_bytes(), 84 * lx * ly);
        assert_eq!(lattice.device_bytes(), 16 * (lx * ly + lx + ly));
        assert_eq!(
            direct.device_bytes(),
            (9 * lx * ly).next_multiple_of(16) + 16 * (lx + ly)
        );
        // Chains that end on the bilinear interpolant against chains from a constant seed:
        // within the sum of their bounds, with the tolerance reached in fewer steps.
        let probe: Vec<[f32; 2]> = (0..997)
            .map(|i| {
                [
                    (i as f32 * 0.618_034).fract(),
                    (i as f32 * 0.414_214).fract(),
                ]
            })
            .collect();
        let ended = decode::points(&op, &probe, 400, 1e-3);
        let seeded = decode::points(&Stepwise(&op), &probe, 400, 1e-3);
        let (mut fewer, mut steps) = (0u32, 0u32);
        for (a, b) in ended.iter().zip(&seeded) {
            assert!(
                (a.value - b.value).abs() <= a.error_bound + b.error_bound,
                "{w}x{h}: {} within {} against {} within {}",
                a.value,
                a.error_bound,
                b.value,
                b.error_bound
            );
            fewer += a.iterations;
            steps += b.iterations;
        }
        assert!(
            fewer < steps || op.roughness() == 0.0,
            "{w}x{h}: {fewer} steps against {steps}"
        );
    }
}

/// The operator stepped as every other codec's is (the default `run_chains`, a constant
/// seed): what the flattening for the GPU reproduces.
struct Stepwise<'a>(&'a ProjectedOperator);

impl Operator<2> for Stepwise<'_> {
    fn frame(&self) -> [f32; 2] {
        self.0.frame()
    }
    fn valid(&self) -> [f32; 2] {
        self.0.valid()
    }
    fn expansion(&self) -> u32 {
        self.0.expansion()
    }
    fn step(&self, p: [f32; 2]) -> Step<2> {
        self.0.step(p)
    }
    fn invariant_interval(&self) -> (f32, f32) {
        self.0.invariant_interval()
    }
}

impl crate::core::pieces::Flatten for Stepwise<'_> {
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        self.0.pieces()
    }
}

#[test]
fn a_grid_codes_within_half_a_step_and_decodes_as_coded() {
    let (w, h) = (37, 29);
    let g = grid(w, h);
    // Both codings: format 9's two-rate contexts, and formats 5-8's one-rate ones (still read).
    for order in [
        pyramid::Order::Separable,
        pyramid::Order::Quincunx,
        pyramid::Order::SeparableTwoRate,
        pyramid::Order::QuincunxTwoRate,
    ] {
        let hd = ProjectedHeader {
            order,
            ..header(w, h, &g)
        };
        let (stream, coded) = encode_grid(&hd, &g, None, (0.0, 0.0));
        let decoded = decode_grid(&hd, &stream).expect("decode");
        assert_eq!(
            coded, decoded,
            "{order:?}: the decoder walks as the encoder did"
        );
        for (a, b) in decoded.iter().zip(&g) {
            assert!((a - b).abs() <= 0.5 + 1e-9, "{order:?}: {a} for {b}");
        }
    }
}

/// A coarse view: the pyramid's samples on multiples of 2^depth, bit for bit the full
/// decode's there, with the plane's promise; a lifted plane's, the low-pass of the decoded grid at that depth (in
/// source units: a plane's view of a plane is that plane), and close to the source's own
/// low-pass at a fine step.
#[test]
fn coarse_views_are_the_coarse_samples_of_the_multiresolution() {
    let (w, h) = (45, 38);
    let g = grid(w, h);
    for depth in 1..=3u32 {
        let s = 1usize << depth;
        let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
        let hd = header(w, h, &g);
        let (stream, _) = encode_grid(&hd, &g, None, (0.0, 0.0));
        let full = decode_grid(&hd, &stream).unwrap();
        let (view, coarse, read) = decode_coarse(&hd, &stream, depth).unwrap();
        // The bytes it says it read are all it needs.
        let (_, again, _) = decode_coarse(&hd, &stream[..read], depth).unwrap();
        assert_eq!(
            again,
            coarse,
            "pyramid {depth}: {read} of {} bytes",
            stream.len()
        );
        assert_eq!(view.samples, [cw as u32, ch as u32]);
        // A pyramid's view is source cells decoded within the plane's bound: its promise.
        assert_eq!(
            view.promise(),
            hd.promise(),
            "a view keeps its samples' bound"
        );
        for (k, v) in coarse.iter().enumerate() {
            assert_eq!(*v, full[(k / cw) * s * w + (k % cw) * s], "pyramid {depth}");
        }
        let plane: Vec<f64> = (0..w * h)
            .map(|i| 100.0 + 3.0 * (i % w) as f64 - 2.0 * (i / w) as f64)
            .collect();
        for (order, kernel) in [
            (pyramid::Order::Lifted, kernel::Kernel::Fitted),
            (pyramid::Order::Lifted97, kernel::Kernel::Cdf97),
            (pyramid::Order::LiftedTwoRate, kernel::Kernel::Fitted),
            (pyramid::Order::Lifted97TwoRate, kernel::Kernel::Cdf97),
        ] {
            for (source, step) in [(&plane, 0.01), (&g, 0.01)] {
                let hd = ProjectedHeader {
                    order,
                    max_error: 0.0,
                    step,
                    ..header(w, h, source)
                };
                let (stream, _) = encode_grid(&hd, source, None, (0.0, 0.0));
                let (_, coarse, read) = decode_coarse(&hd, &stream, depth).unwrap();
                let (_, again, _) = decode_coarse(&hd, &stream[..read], depth).unwrap();
                assert_eq!(
                    again, coarse,
                    "{kernel:?} {depth}: a prefix of {read} bytes"
                );
                let lp = lifting::analysis(&lifted_plane(&hd.layout(), kernel), source, depth);
                // Past the plane's levels (2 here), its coarsest samples are taken.
                let read = depth.min(u32::from(hd.levels));
                let gain = kernel::dc_gain(kernel).powi(2 * read as i32);
                for (k, v) in coarse.iter().enumerate() {
                    let (x, y) = ((k % cw) * s, (k / cw) * s);
                    let want = lp[y * w + x] / gain;
                    assert!(
                        (v - want).abs() < 0.05,
                        "{kernel:?} {depth}: {v} for {want}"
                    );
                    if std::ptr::eq(source, &plane) {
                        // Away from the mirrored ends a low-pass of a plane is the plane.
                        let inside = x >= 8 && y >= 8 && x + 8 < w && y + 8 < h;
                        let at = source[y * w + x];
                        assert!(!inside || (v - at).abs() < 0.05, "{kernel:?}: {v} for {at}");
                    }
                }
            }
        }
    }
}

#[test]
fn roughness_is_none_on_a_cubic_and_high_on_noise() {
    let (w, h) = (64, 64);
    // A cubic's midpoint residual is zero: no roughness at all.
    let cubic: Vec<f64> = (0..w * h)
        .map(|i| ((i % w) as f64).powi(3) * 1e-3 + (i / w) as f64)
        .collect();
    assert!(fit_roughness(&cubic, w, h) < 0.05);
    // White noise has the same residual at every spacing: the most rho allows.
    assert!(fit_roughness(&grid(w, h), w, h) > 0.7);
}
