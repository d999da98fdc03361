#pragma once
/// Labelled cells painted into generated sections at known positions (issue 22): the ground
/// truth of the cell counting. Used by both generator families (GeneratorOptions::cells,
/// GeneratorOptionsB::cells); off by default, and turning it on changes nothing else of a
/// section (its own random stream), apart from the cells painted.
///
/// Units: image pixels, pixel centres at integers, origin top-left. Re-entrant; deterministic.

#include <opencv2/core.hpp>

#include <cstdint>
#include <vector>

namespace slicestation::sim {

struct CellOptions {
    bool enabled = false;
    double diameterPx = 6; ///< cell body diameter (the blob's full width at half maximum)
    /// Mean cells per 10^6 px of tissue; each region's density is this times a factor in
    /// [0.1, 2.0] drawn from its id and the seed (regions differ, as labelled populations do).
    double meanPerMpx = 1500;
    /// Peak of a cell over the tissue around it. Fluorescence: in units of the brightest
    /// region's stain level (family 2: of the stain amount), brighter. Brightfield: family 1
    /// paints a DAB-like brown of this optical density (blue channel most); family 2 adds this
    /// much of its own stain. 2 makes labelled cells stand out as immunolabelled cells do.
    double contrast = 2.0;
    /// Nearest allowed centre distance, x diameterPx: cell bodies do not overlap much, but touch
    /// (clusters to split). In [0.5, 3].
    double minDistance = 0.8;
};

struct TrueCell {
    cv::Point2d image;        ///< centre, image px (sub-pixel)
    std::int32_t atlasId = 0; ///< the label under the centre through the true map
    /// False when the cell is not in intact tissue at the end (in damage, missing tissue or a
    /// moved fragment): it is not to be counted.
    bool counted = true;
};

/// Places cells over the tissue (`labels` > 0 where `tissue` != 0, CV_32S and CV_8U of one size)
/// with densities per region, at least minDistance x diameter apart.
std::vector<TrueCell> placeCells(const cv::Mat& labels, const cv::Mat& tissue,
                                 const CellOptions& options, std::uint64_t seed);

/// Unit-peak Gaussian blobs (CV_32F, `size`) at the cells' centres, FWHM = diameterPx.
cv::Mat renderCells(cv::Size size, const std::vector<TrueCell>& cells, double diameterPx);

/// Sets TrueCell::counted: the centre is on `tissueAfter` (CV_8U != 0) and not on
/// `damageMask` (CV_8U != 0).
void markCounted(std::vector<TrueCell>& cells, const cv::Mat& tissueAfter,
                 const cv::Mat& damageMask);

} // namespace slicestation::sim
