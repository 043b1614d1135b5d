//! Meshes simplified to an error: edge collapses by meshoptimizer (zeux's library through the
//! `meshopt` crate: a maintained, widely used simplifier; nothing here is worth writing again),
//! their open borders kept where they are, so that meshes that meet along a border (a 3D
//! tile's and its neighbour's) still meet after.

use crate::mesh::Mesh;

impl Mesh {
    /// The mesh with as few triangles as keep it within about `max_error` (world units) of
    /// itself, its border vertices fixed; unused vertices dropped, normals kept with their
    /// vertices. meshoptimizer measures the error by quadrics, an estimate of the distance and
    /// not a bound: callers that state an error measure it (the 3D tiles' test does, against
    /// the source mesh).
    pub fn simplified(&self, max_error: f64) -> Mesh {
        if self.triangles.is_empty() || max_error.is_nan() || max_error <= 0.0 {
            return self.clone();
        }
        let indices: Vec<u32> = self.triangles.iter().flatten().copied().collect();
        // meshoptimizer takes the error relative to the mesh's extent.
        let bytes: Vec<u8> = self
            .positions
            .iter()
            .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
            .collect();
        let Ok(adapter) = meshopt::VertexDataAdapter::new(&bytes, 12, 0) else {
            return self.clone();
        };
        let scale = meshopt::simplify_scale(&adapter);
        if scale.is_nan() || scale <= 0.0 {
            return self.clone();
        }
        let kept = meshopt::simplify(
            &indices,
            &adapter,
            0,
            (max_error / f64::from(scale)) as f32,
            meshopt::SimplifyOptions::LockBorder,
            None,
        );
        // Only the vertices the kept triangles use, in their first use's order.
        let mut remap = vec![u32::MAX; self.positions.len()];
        let mut out = Mesh::default();
        let has_normals = self.has_normals();
        let triangles = kept
            .chunks_exact(3)
            .map(|t| {
                [t[0], t[1], t[2]].map(|v| {
                    let slot = &mut remap[v as usize];
                    if *slot == u32::MAX {
                        *slot = out.positions.len() as u32;
                        out.positions.push(self.positions[v as usize]);
                        if has_normals {
                            out.normals.push(self.normals[v as usize]);
                        }
                    }
                    *slot
                })
            })
            .collect();
        out.triangles = triangles;
        out
    }
}
