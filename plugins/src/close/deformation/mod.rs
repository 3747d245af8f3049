//! `deformation`: local loop closure between the active and the inactive model and the
//! non-rigid correction of the map by an embedded deformation graph (the paper's "Deformation
//! graph" and "Loop closure"; ElasticFusion, `shared/design/elasticfusion.md` §4–5).

pub mod graph;

#[cfg(test)]
mod graph_tests;
