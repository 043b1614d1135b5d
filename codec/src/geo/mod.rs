//! Where tile pixels fall on an asset: Web Mercator (EPSG:3857, XYZ scheme, y down from the
//! north) tile geometry, and the mapping from longitude/latitude to an asset's unit square
//! through its georeference (`placement`), and a raster's pixels on it (`pixels`). Assets
//! without a georeference are tiled over the unit square.

mod pixels;
mod placement;

// Tile addresses are the wire's vocabulary: one copy of the Web Mercator formulas, in proto.
pub use fractile_proto::tiles::{MAX_LATITUDE, lonlat_tile, tile_bounds, tile_lonlat};
pub use pixels::*;
pub use placement::*;

#[cfg(test)]
mod tests {
    use super::placement::Crs;
    use super::*;
    use fractile_proto::Georef;

    /// The common CRSs a build without the EPSG registry places (the browser's) are the
    /// registry's own definitions, parsed to the same projection.
    #[cfg(feature = "epsg")]
    #[test]
    fn common_crs_are_the_registrys() {
        use proj4rs::proj::Proj;
        let codes = [4326, 4269, 4258, 3857]
            .into_iter()
            .chain(32601..=32660)
            .chain(32701..=32760)
            .chain(26901..=26923)
            .chain(25828..=25838);
        let mut n = 0;
        for code in codes {
            let ours = Proj::from_proj_string(&common_crs(code).unwrap()).unwrap();
            let registry = Proj::from_epsg_code(code as u16).unwrap();
            assert_eq!(format!("{ours:?}"), format!("{registry:?}"), "EPSG:{code}");
            n += 1;
        }
        assert_eq!(n, 4 + 60 + 60 + 23 + 11);
        assert!(common_crs(4087).is_none());
    }

    /// The EPSG registry's own kinds (not a number range): 4087 is projected though it lies in
    /// 4000-4999.
    #[test]
    fn geographic_crs_are_told_by_their_definition() {
        assert_eq!(epsg_is_geographic(4326), Some(true));
        assert_eq!(epsg_is_geographic(4269), Some(true));
        assert_eq!(epsg_is_geographic(4087), Some(false));
        assert_eq!(epsg_is_geographic(32616), Some(false));
        assert_eq!(epsg_is_geographic(3857), Some(false));
        assert_eq!(epsg_is_geographic(99999), None);
    }

    #[test]
    fn tile_geometry_matches_the_web_mercator_definition() {
        // Zoom 0 covers the whole world; its centre is (0, 0).
        let (lon, lat) = tile_lonlat(0, 0, 0, 0.5, 0.5);
        assert!(lon.abs() < 1e-9 && lat.abs() < 1e-9);
        let [w, s, e, n] = tile_bounds(0, 0, 0);
        assert!((w + 180.0).abs() < 1e-9 && (e - 180.0).abs() < 1e-9);
        assert!((n - MAX_LATITUDE).abs() < 1e-9 && (s + MAX_LATITUDE).abs() < 1e-9);
        // Round trip through the tile index at zoom 12 (Jacksboro, Tennessee).
        let (x, y) = lonlat_tile(12, -84.2, 36.4);
        let [w, s, e, n] = tile_bounds(12, x, y);
        assert!(w <= -84.2 && -84.2 < e && s < 36.4 && 36.4 <= n);
    }

    #[test]
    fn global_assets_wrap_at_the_antimeridian() {
        let g = Georef {
            epsg: Some(4326),
            origin: [-180.0, 90.0],
            pixel_size: [1.0 / 3.0, -1.0 / 3.0],
        };
        let p = Placement::of(&g, 1080, 540).unwrap();
        let a = p.unit(179.999, 0.0).unwrap();
        let b = p.unit(-179.999, 0.0).unwrap();
        assert!(a[0] > 0.999 && b[0] < 0.001);
        assert!(p.unit(0.0, 91.0).is_none());
        // Codes outside the EPSG registry are refused (the server then tiles the unit square).
        let unknown = Georef {
            epsg: Some(99_999),
            ..g
        };
        assert_eq!(
            Placement::of(&unknown, 10, 10).unwrap_err(),
            PlacementError::UnknownCrs(99_999)
        );
    }

    /// A frame of 1,000 x 1,000 cells of `cell` CRS units whose south-west corner is at
    /// `(east, north)` minus half the frame.
    fn frame(epsg: u32, centre: [f64; 2], cell: f64) -> Placement {
        let g = Georef {
            epsg: Some(epsg),
            origin: [centre[0] - 500.0 * cell, centre[1] + 500.0 * cell],
            pixel_size: [cell, -cell],
        };
        Placement::of(&g, 1000, 1000).unwrap()
    }

    #[test]
    fn projected_placements_agree_with_proj() {
        // Reference coordinates from PROJ 9 (`cs2cs EPSG:4326 EPSG:32616` and `EPSG:2154`),
        // an implementation independent of ours.
        for (epsg, (lon, lat), (x, y)) in [
            (32616, (-84.2, 36.4), (751106.6077, 4031958.4991)),
            (2154, (2.35, 49.0), (652438.8715, 6877982.4576)),
        ] {
            // A 30 km frame whose centre is 1 km south-west of the point.
            let p = frame(epsg, [x - 1000.0, y - 1000.0], 30.0);
            assert_eq!(p.epsg(), Some(epsg));
            let [u, v] = p.unit(lon, lat).unwrap();
            // 0.5 + 1000 m / 30,000 m east; 0.5 - 1000 / 30,000 south (v grows southwards).
            let (eu, ev) = (0.5 + 1.0 / 30.0, 0.5 - 1.0 / 30.0);
            assert!(
                (u as f64 - eu).abs() * 30_000.0 < 0.01 && (v as f64 - ev).abs() * 30_000.0 < 0.01,
                "EPSG:{epsg}: ({u}, {v}) against ({eu}, {ev})"
            );
            // Its lon/lat box holds the point and is about 30 km across.
            let [w, s, e, n] = p.bounds();
            assert!(w < lon && lon < e && s < lat && lat < n);
            let km_ns = (n - s) * metres_per_degree(lat)[1] / 1000.0;
            assert!((29.5..31.5).contains(&km_ns), "{km_ns} km");
            // Far points are outside, not folded onto the frame by the projection.
            assert!(p.unit(lon + 180.0, -lat).is_none());
            assert!(p.unit(lon + 1.0, lat).is_none());
        }
    }

    #[test]
    fn interpolated_reprojection_is_within_an_eighth_of_a_pixel() {
        // UTM 16N around Jacksboro, 30 m cells, and a 1,000 km frame of the north polar
        // stereographic CRS (EPSG:3413) at 75N, 0E, where meridians fan out and parallels bend:
        // low zooms there need the per-pixel fallback. Tiles from a zoom that holds the whole
        // frame in a few pixels down to deeper than its cells, centred on the frame and on its
        // north-west corner (so some pixels are outside).
        let utm = frame(32616, [751_106.6, 4_031_958.5], 30.0);
        let polar = Placement::of(
            &Georef {
                epsg: Some(3413),
                origin: [0.0, 0.0],
                pixel_size: [1.0, -1.0],
            },
            1,
            1,
        )
        .unwrap();
        let Crs::Projected(stereo) = &polar.crs else {
            panic!("EPSG:3413 is projected");
        };
        let centre = stereo.forward(0.0, 75.0).unwrap();
        let polar = frame(3413, centre, 1000.0);
        for (p, zooms) in [
            (&utm, &[4u8, 8, 10, 12, 15, 17][..]),
            (&polar, &[2, 3, 4, 5, 8, 11][..]),
        ] {
            check_tiles(p, zooms);
        }
    }

    fn check_tiles(p: &Placement, zooms: &[u8]) {
        let [w, s, e, n] = p.bounds();
        let Crs::Projected(projection) = &p.crs else {
            panic!("UTM is projected");
        };
        let [cw, cn] = projection.inverse(p.west, p.north).unwrap();
        for &z in zooms {
            for (lon, lat) in [(0.5 * (w + e), 0.5 * (s + n)), (cw, cn)] {
                let (x, y) = lonlat_tile(z, lon, lat);
                let px = tile_pixels(Some(p), z, x, y, 256, 0);
                let Sites::List {
                    width,
                    points,
                    patches,
                } = &px.sites
                else {
                    panic!("projected assets give a point per pixel");
                };
                assert_eq!((*width, points.len()), (256, 256 * 256));
                // Patches are disjoint, inside the tile, and give the listed points.
                let mut covered = vec![false; points.len()];
                for pa in patches {
                    for j in 0..pa.patch.height {
                        for i in 0..pa.patch.width {
                            let k = (pa.row + j) * 256 + pa.col + i;
                            assert!(pa.col + i < 256 && !covered[k], "z{z}: pixel {k} twice");
                            covered[k] = true;
                            if let Some(q) = points[k] {
                                let at = pa.patch.at(i, j);
                                assert!(
                                    (q[0] as f64 - at[0]).abs() < 1e-6
                                        && (q[1] as f64 - at[1]).abs() < 1e-6
                                );
                            }
                        }
                    }
                }
                // Where the reprojection is smooth at the tile's scale (and lattice cells are
                // small beside the frame), every pixel on the asset is in one.
                if p.epsg() == Some(32616) && z >= 12 {
                    let loose = (0..covered.len()).filter(|&k| points[k].is_some() && !covered[k]);
                    assert_eq!(loose.count(), 0, "z{z}: pixels decoded one by one");
                }
                let f = px.footprint;
                assert!(f[0] > 0.0 && f[1] > 0.0);
                let mut inside = 0;
                for (k, got) in points.iter().enumerate() {
                    let (fx, fy) = ((k % 256) as f64 + 0.5, (k / 256) as f64 + 0.5);
                    let (plon, plat) = tile_lonlat(z, x, y, fx / 256.0, fy / 256.0);
                    let Some(exact) = p.unit_f64(plon, plat) else {
                        assert!(got.is_none(), "z{z} pixel {k}: far away, yet inside");
                        continue;
                    };
                    let near_edge = exact
                        .iter()
                        .zip(f)
                        .any(|(&t, f)| t.abs() < f as f64 || (t - 1.0).abs() < f as f64);
                    match got {
                        Some(g) => {
                            inside += 1;
                            let (du, dv) = (g[0] as f64 - exact[0], g[1] as f64 - exact[1]);
                            // An eighth of a pixel, plus f32 rounding of unit coordinates.
                            assert!(
                                du.abs() <= 0.125 * f[0] as f64 + 1e-7
                                    && dv.abs() <= 0.125 * f[1] as f64 + 1e-7,
                                "z{z} pixel {k}: ({du}, {dv}) against footprint {f:?}"
                            );
                        }
                        None => assert!(
                            near_edge || p.unit(plon, plat).is_none(),
                            "z{z} pixel {k} is inside"
                        ),
                    }
                }
                assert!(inside > 0, "z{z}: tile {x}/{y} misses the frame");
            }
        }
    }
}
