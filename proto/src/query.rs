//! The closed choices of the HTTP API's query strings, one vocabulary for both ends of the
//! wire: the server parses a query's value with [`FromStr`](std::str::FromStr) (and answers its
//! own error code when that fails), the client writes [`Choice::name`] into its URLs.

use serde::{Deserialize, Serialize};

/// A closed choice of a query parameter.
pub trait Choice: Copy + Sized + 'static {
    /// Every value, in the order the API documents them.
    const ALL: &'static [Self];
    /// The value's name in a query string.
    fn name(self) -> &'static str;
    /// "a, b or c": the names, for error messages.
    fn names() -> String {
        let n: Vec<&str> = Self::ALL.iter().map(|c| c.name()).collect();
        match n.split_last() {
            Some((last, rest)) if !rest.is_empty() => format!("{} or {last}", rest.join(", ")),
            _ => n.join(""),
        }
    }
}

// Hand-written rather than strum's derives: five small enums do not justify a dependency, and
// `Choice::names` gives every refusal the same wording.
macro_rules! choice {
    ($(#[$doc:meta])* $name:ident, $what:literal {
        $($(#[$vdoc:meta])* $variant:ident = $text:literal $(| $alias:literal)*,)+
    }) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
        pub enum $name {
            $($(#[$vdoc])* #[serde(rename = $text $(, alias = $alias)*)] $variant,)+
        }

        impl Choice for $name {
            const ALL: &'static [Self] = &[$($name::$variant),+];
            fn name(self) -> &'static str {
                match self {
                    $($name::$variant => $text,)+
                }
            }
        }

        impl std::str::FromStr for $name {
            type Err = String;
            /// Parses a name (or an accepted alias); the error reads `<what> "<s>": a, b or c`.
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $($text $(| $alias)* => Ok($name::$variant),)+
                    _ => Err(format!("{} {s:?}: {}", $what, Self::names())),
                }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        }
    };
}

choice!(
    /// `encoding` of a PNG tile of a height field: how heights are packed into its channels.
    HeightEncoding, "encoding" {
        /// Mapbox/MapLibre terrain-RGB: `h = -10000 + (R * 65536 + G * 256 + B) * 0.1`.
        TerrainRgb = "terrainrgb",
        /// Terrarium: `h = (R * 256 + G + B / 256) - 32768`.
        Terrarium = "terrarium",
        /// 16-bit grey of the asset's value range.
        Gray16 = "gray16",
    }
);

choice!(
    /// `precision` of a PNG height tile (terrain-RGB or Terrarium).
    #[derive(Default)]
    Precision, "precision" {
        /// Heights rounded to the largest power-of-two multiple of the encoding's unit that
        /// is at most half the tile's `X-Error-Bound` (which then includes the
        /// rounding): neighbouring pixels repeat, and PNG codes them in fewer bytes. Tiles of
        /// assets without a source-error map keep full precision (no bound justifies a step).
        #[default]
        Bound = "bound",
        /// Every height at the encoding's own unit (0.1 m, 1/256 m).
        Full = "full",
    }
);

choice!(
    /// `colormap` of a visual PNG tile of a height field.
    Colormap, "colormap" {
        /// Black to white.
        Gray = "gray" | "grey",
        /// Greens to browns to white, for land.
        Terrain = "terrain",
        /// Perceptually uniform blue-green-yellow.
        Viridis = "viridis",
    }
);

choice!(
    /// `backend`: where the server decodes a request (default: the server's setting, `auto`
    /// unless configured).
    #[derive(Default)]
    Backend, "backend" {
        /// Always the CPU.
        Cpu = "cpu",
        /// The GPU for every continuous decode.
        Gpu = "gpu",
        /// The GPU when it pays (work of a 256 x 256 tile or more on a hardware adapter).
        #[default]
        Auto = "auto",
    }
);

choice!(
    /// `format` of a region (default png).
    #[derive(Default)]
    RegionFormat, "format" {
        /// A visual PNG (heights as grey over their range).
        #[default]
        Png = "png",
        /// Little-endian float32 values, channel after channel, row-major, NaN for nodata.
        F32 = "f32",
        /// A float32 GeoTIFF georeferenced to the box (height fields).
        Tif = "tif",
    }
);

choice!(
    /// `format` of a mesh (default glb).
    #[derive(Default)]
    MeshFormat, "format" {
        /// Wavefront OBJ (text).
        Obj = "obj",
        /// Binary little-endian PLY.
        Ply = "ply",
        /// glTF 2.0 binary.
        #[default]
        Glb = "glb",
    }
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_back_and_refusals_list_the_choices() {
        for b in Backend::ALL {
            assert_eq!(b.name().parse::<Backend>(), Ok(*b));
            assert_eq!(
                serde_json::to_string(b).unwrap(),
                format!("\"{}\"", b.name())
            );
        }
        assert_eq!(
            "tpu".parse::<Backend>(),
            Err("backend \"tpu\": cpu, gpu or auto".to_string())
        );
        assert_eq!("TIF".parse::<RegionFormat>().ok(), None);
        assert_eq!("terrainrgb".parse(), Ok(HeightEncoding::TerrainRgb));
        assert_eq!("grey".parse(), Ok(Colormap::Gray));
        assert_eq!(Colormap::Gray.name(), "gray");
    }
}
