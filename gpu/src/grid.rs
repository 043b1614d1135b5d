//! The grids a dispatch decodes: a window of pixel centres or a separable grid, and their
//! axes as the kernels read them.

/// Where a dispatch's points come from.
#[derive(Clone, Debug, PartialEq)]
pub enum Grid {
    /// A `width x height` grid over the unit-square window `[u0, v0, u1, v1]` (pixel centres).
    Window {
        /// `[u0, v0, u1, v1]`.
        rect: [f32; 4],
        /// Points a row.
        width: u32,
        /// Rows.
        height: u32,
    },
    /// A separable grid: point (i, j) is `(xs[i], ys[j])` in unit coordinates. The pixels of a
    /// Web Mercator tile over an asset placed in lon/lat are one.
    Separable {
        /// Unit x of each column.
        xs: Vec<f32>,
        /// Unit y of each row.
        ys: Vec<f32>,
    },
}

impl Grid {
    /// Points a row and rows.
    pub fn size(&self) -> (u32, u32) {
        match self {
            Grid::Window { width, height, .. } => (*width, *height),
            Grid::Separable { xs, ys } => (xs.len() as u32, ys.len() as u32),
        }
    }
}

/// A grid's width, height and axes (unit x of each column, then unit y of each row).
pub(crate) fn grid_axes(grid: &Grid) -> (u32, u32, Vec<f32>) {
    match grid {
        // A window is the separable grid of its pixel centres, made as the CPU makes them
        // (in f64, rounded once): both must start every chain at the same f32 point.
        Grid::Window {
            rect,
            width,
            height,
        } => {
            let (xs, ys) =
                fractile_codec::decode::window_axes(*rect, *width as usize, *height as usize);
            (
                *width,
                *height,
                xs.into_iter().chain(ys).collect::<Vec<f32>>(),
            )
        }
        Grid::Separable { xs, ys } => (
            xs.len() as u32,
            ys.len() as u32,
            xs.iter().chain(ys).copied().collect::<Vec<f32>>(),
        ),
    }
}
