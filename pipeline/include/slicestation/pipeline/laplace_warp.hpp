#pragma once
/// The non-linear warp of the paper (section 3.2.3, "Local Alignment using Laplacian"): each
/// displacement component solves Laplace's equation with the tight correspondences as Dirichlet
/// conditions. Solved coarse to fine on a node grid instead of one sparse system on every pixel,
/// which the paper reports at about 100 s and 4 GB for 2115x2731 px.

#include <opencv2/core.hpp>

#include <vector>

namespace slicestation::pipeline {

/// A smooth displacement field over a rectangular domain, sampled on nodes spaced `cellPx`
/// apart (node (i, j) sits at x = j * cellPx, y = i * cellPx) and interpolated bilinearly.
/// An empty field is zero everywhere.
class DisplacementField {
public:
    DisplacementField() = default;
    DisplacementField(cv::Mat dx, cv::Mat dy, double cellPx);

    bool empty() const { return dx_.empty(); }
    /// Displacement at a domain point (bilinear; clamped outside the grid).
    cv::Point2d at(cv::Point2d p) const;
    const cv::Mat& dx() const { return dx_; }
    const cv::Mat& dy() const { return dy_; }
    double cellPx() const { return cellPx_; }

private:
    cv::Mat dx_, dy_; ///< CV_32F node values
    double cellPx_ = 1.0;
};

struct LaplaceOptions {
    double cellPx = 4.0;      ///< finest node spacing, domain pixels
    int coarsestNodes = 12;   ///< stop coarsening when the short side has this few nodes
    int sweepsCoarsest = 400; ///< SOR sweeps on the coarsest grid
    int sweepsPerLevel = 40;  ///< SOR sweeps after each refinement
    double relaxation = 1.85; ///< SOR factor
};

/// Solves for the field that equals `displacements[k]` at `points[k]` (domain pixels; several
/// points falling on one node are averaged) and is harmonic elsewhere, with natural (Neumann)
/// borders. With no points the field is empty.
DisplacementField solveLaplaceWarp(cv::Size domain, const std::vector<cv::Point2d>& points,
                                   const std::vector<cv::Point2d>& displacements,
                                   const LaplaceOptions& options = {});

/// `field` with the nodes under `region` (CV_8U, the field's node grid, nonzero = free)
/// replaced by the harmonic interpolation of the nodes around them: every other node is held,
/// the free ones relaxed by `sweeps` SOR sweeps of the same five-point Laplacian (mirror
/// borders at the grid's edge). Nothing outside `region` changes.
DisplacementField relaxWithin(const DisplacementField& field, const cv::Mat& region,
                              int sweeps = 200, double relaxation = 1.85);

} // namespace slicestation::pipeline
