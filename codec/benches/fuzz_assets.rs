//! Fuzzes the asset reader for as long as asked: the mutations of `tests/hostile.rs` (bytes,
//! sizes and lengths overwritten, cuts, insertions, checksums made valid again) applied to a
//! valid small asset of every codec, each mutant read under the fuzz limits and, if accepted,
//! decoded a little. A panic stops the run with the mutant's seed; at the end it prints a table
//! per codec: mutants, accepted, refused, slowest read-and-decode.
//!
//! `cargo bench -p fractile-codec --bench fuzz_assets -- [cases per codec, default 20000] [seed]`
//! (`FUZZ_EXTRA=a.fra:b.fra` adds more sources, such as held-out data encoded by the CLI)
//! (libFuzzer through cargo-fuzz needs a nightly toolchain, which CI has not: this runs the
//! same kind of search on stable, with a seeded generator so a failure can be replayed.)

#[path = "../tests/support/hostile.rs"]
mod hostile;

use std::time::{Duration, Instant};

use hostile::*;

/// xorshift64*: a seeded stream of numbers, so that a failing mutant can be replayed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

fn mutation(rng: &mut Rng, len: usize) -> Mutation {
    // Half of the positions fall in the first 256 bytes: the headers, where sizes live.
    let at = if rng.below(2) == 0 {
        rng.below(256.min(len as u64)) as usize
    } else {
        rng.below(len as u64) as usize
    };
    match rng.below(5) {
        0 => Mutation::Byte(at, rng.next() as u8),
        1 => Mutation::Word(at, WORDS[rng.below(WORDS.len() as u64) as usize]),
        2 => Mutation::Word(at, rng.next() as u32),
        3 => Mutation::Truncate(at),
        _ => {
            let n = 1 + rng.below(16) as usize;
            Mutation::Insert(at, (0..n).map(|_| rng.next() as u8).collect())
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let cases: usize = args.first().and_then(|a| a.parse().ok()).unwrap_or(20_000);
    let seed: u64 = args
        .get(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(0x9E37_79B9_7F4A_7C15);
    // Held-out assets too (files not in the repository, encoded by `fractile encode`):
    // FUZZ_EXTRA=a.fra:b.fra.
    let mut sources: Vec<(String, Vec<u8>)> = sources()
        .into_iter()
        .map(|(n, b)| (n.to_string(), b))
        .collect();
    for path in std::env::var("FUZZ_EXTRA")
        .unwrap_or_default()
        .split(':')
        .filter(|p| !p.is_empty())
    {
        let name = std::path::Path::new(path)
            .file_name()
            .map_or(path.into(), |n| n.to_string_lossy().into_owned());
        sources.push((name, std::fs::read(path).expect("a FUZZ_EXTRA file")));
    }
    println!("fuzzing the asset reader: {cases} mutants per codec, seed {seed}\n");
    println!("| codec | source bytes | mutants | accepted | refused | slowest | mutants/s |");
    println!("|---|---|---|---|---|---|---|");
    let mut rng = Rng(seed);
    for (name, source) in &sources {
        let (mut accepted, mut slowest) = (0usize, Duration::ZERO);
        let start = Instant::now();
        for _ in 0..cases {
            let count = 1 + rng.below(3) as usize;
            let mutations: Vec<Mutation> = (0..count)
                .map(|_| mutation(&mut rng, source.len()))
                .collect();
            let bytes = mutate(source, &mutations);
            let t = Instant::now();
            let ok = std::panic::catch_unwind(|| exercise(&bytes)).unwrap_or_else(|_| {
                eprintln!("PANIC on {name} with {mutations:?}");
                std::process::exit(1);
            });
            slowest = slowest.max(t.elapsed());
            accepted += usize::from(ok);
        }
        let secs = start.elapsed().as_secs_f64();
        println!(
            "| {name} | {} | {cases} | {accepted} | {} | {:.1} ms | {:.0} |",
            source.len(),
            cases - accepted,
            slowest.as_secs_f64() * 1e3,
            cases as f64 / secs
        );
    }
}
