#pragma once
/// Exterior medial axis of a closed outline through a constrained Delaunay triangulation
/// (paper Algorithm 2, lines 1-4).

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// A connected piece of the exterior medial axis: the Voronoi vertices (circumcentres of kept
/// exterior triangles) joined by Voronoi edges that cross no outline edge.
struct MedialBranch {
    double length = 0;                ///< longest path through the piece (its depth into a pocket)
    std::vector<int> outlineVertices; ///< outline vertices of the triangles on this piece
    std::vector<cv::Point2d> axis;    ///< the Voronoi vertices (for drawing and tests)
};

struct ExteriorTriangulation {
    int insideFaces = 0;   ///< faces marked inside the outline
    int exteriorFaces = 0; ///< finite faces outside the outline (within its convex hull)
    int keptFaces = 0;     ///< exterior faces whose circumcentre lies inside them (the others
                           ///< join the axis only through the middle of their longest edge)
    std::vector<MedialBranch> branches; ///< every piece, longest first
};

/// Triangulates the closed polygon `outline` (vertices in order, no repeat of the first at the
/// end) with its edges as constraints, marks inside and outside faces by a flood fill from the
/// infinite face that flips at every constrained edge (Debian's CGAL 5.5 has no
/// mark_domain_in_triangulation), and joins the exterior triangles' circumcentres across
/// unconstrained edges into medial-axis pieces. Skinny triangles (circumcentre outside) stand
/// in with the middle of their longest edge so they do not cut the axis.
ExteriorTriangulation exteriorMedialAxis(const std::vector<cv::Point2f>& outline);

} // namespace slicestation::pipeline
