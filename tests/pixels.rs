//! `browser-pixels`: judges a screenshot of the web viewer by its pixels, for `tests/browser.sh`.
//!
//! The page is a bar across the top and side-by-side map panels below it. For each panel, the
//! share of pixels that differ from the panel's most common colour (its background, when a map
//! drew nothing) must reach the given minimum: a map that loaded no tiles, or a coast map with
//! no line, is one flat colour. Each panel's label (top) and attribution (bottom) are left out.
//!
//! Usage: `browser-pixels SHOT.png BAR_PX LABEL_PX FOOT_PX name:min_share ...` (one per panel, left to
//! right). Prints one line per panel and exits 1 if any panel is under its minimum.
//! `browser-pixels --changed BEFORE.png SHOT.png ...` (the same arguments after) counts instead
//! the pixels of each panel that differ between the two screenshots: a view that changed.

use std::collections::HashMap;
use std::process::ExitCode;

/// Channels may differ by this much and still count as the background (antialiasing, dithering
/// of software WebGL).
const SAME_COLOUR: i32 = 12;

fn main() -> ExitCode {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let before = match args.first().map(String::as_str) {
        Some("--changed") if args.len() > 2 => {
            let path = args.remove(1);
            args.remove(0);
            match image::open(&path) {
                Ok(img) => Some(img.to_rgb8()),
                Err(e) => {
                    eprintln!("{path}: {e}");
                    return ExitCode::from(2);
                }
            }
        }
        _ => None,
    };
    if args.len() < 5 {
        eprintln!("usage: browser-pixels SHOT.png BAR_PX LABEL_PX FOOT_PX name:min_share ...");
        return ExitCode::from(2);
    }
    let shot = match image::open(&args[0]) {
        Ok(img) => img.to_rgb8(),
        Err(e) => {
            eprintln!("{}: {e}", args[0]);
            return ExitCode::from(2);
        }
    };
    let (bar, label, foot): (u32, u32, u32) =
        match (args[1].parse(), args[2].parse(), args[3].parse()) {
            (Ok(b), Ok(l), Ok(f)) => (b, l, f),
            _ => {
                eprintln!("BAR_PX, LABEL_PX and FOOT_PX are pixel counts");
                return ExitCode::from(2);
            }
        };
    let panels: Vec<(&str, f64)> = match args[4..]
        .iter()
        .map(|a| {
            let (name, min) = a.split_once(':')?;
            Some((name, min.parse().ok()?))
        })
        .collect::<Option<_>>()
    {
        Some(p) => p,
        None => {
            eprintln!("panels are name:min_share, e.g. coast:0.002");
            return ExitCode::from(2);
        }
    };
    let (w, h) = shot.dimensions();
    let top = bar + label;
    let bottom = h.saturating_sub(foot);
    if top >= bottom {
        eprintln!("the screenshot is {w}x{h}: no room below the bar and labels");
        return ExitCode::from(2);
    }
    let mut ok = true;
    let width = w / panels.len() as u32;
    for (i, (name, min_share)) in panels.iter().enumerate() {
        let xs = i as u32 * width..(i as u32 + 1) * width;
        let pixels: Vec<[u8; 3]> = xs
            .flat_map(|x| (top..bottom).map(move |y| (x, y)))
            .map(|(x, y)| shot.get_pixel(x, y).0)
            .collect();
        let mut counts: HashMap<[u8; 3], usize> = HashMap::new();
        for p in &pixels {
            *counts.entry(*p).or_default() += 1;
        }
        let background = counts
            .iter()
            .max_by_key(|(_, n)| **n)
            .map(|(c, _)| *c)
            .unwrap_or_default();
        let differs = |p: &[u8; 3], q: &[u8; 3]| {
            (0..3).any(|c| (p[c] as i32 - q[c] as i32).abs() > SAME_COLOUR)
        };
        let drawn = match &before {
            None => pixels.iter().filter(|p| differs(p, &background)).count(),
            Some(b) if b.dimensions() == shot.dimensions() => (i as u32 * width
                ..(i as u32 + 1) * width)
                .flat_map(|x| (top..bottom).map(move |y| (x, y)))
                .filter(|&(x, y)| differs(&shot.get_pixel(x, y).0, &b.get_pixel(x, y).0))
                .count(),
            Some(_) => 0,
        };
        let share = drawn as f64 / pixels.len().max(1) as f64;
        let pass = share >= *min_share;
        ok &= pass;
        println!(
            "{}: {name}: {:.2}% of its pixels differ from {} #{:02x}{:02x}{:02x} (at least {:.2}% wanted)",
            if pass { "ok" } else { "FAILED" },
            share * 100.0,
            if before.is_some() {
                "the first screenshot; its background"
            } else {
                "its background"
            },
            background[0],
            background[1],
            background[2],
            min_share * 100.0
        );
    }
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}
