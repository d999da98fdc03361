#pragma once
/// Atlas regions in section pixels: which side of the atlas midline each section pixel maps to,
/// and the outline polygons of every (region, side) in a label image at section size (e.g.
/// Registration::warpedLabels). Used by the QuPath export; reusable wherever regions are needed
/// in image pixels (areas per region, cells per region). Pure computation, re-entrant.

#include "slicestation/pipeline/atlas_slicing.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <vector>

namespace slicestation::pipeline {

/// The atlas side of every pixel given its atlas coordinates (CV_32F maps, e.g. from
/// Registration::atlasMaps): CV_8U, 1 where the atlas point's left-right coordinate (the atlas
/// frame's third axis, micrometres, along `slice`) is at or above `midlineLrUm`, 0 below.
cv::Mat atlasSideMap(const cv::Mat& mapX, const cv::Mat& mapY, const SliceGeometry& slice,
                     double midlineLrUm);

/// One 4-connected piece of a region: its outer ring and its holes, traced along the pixels'
/// edges, so the polygon's area is exactly the piece's pixel count. Points are pixel corners in
/// pixel-centre coordinates (x.5, y.5), one per corner (collinear points dropped), the ring not
/// repeated at the end; outer rings clockwise on the screen (y down), holes counter-clockwise.
/// Rings of diagonal neighbours may touch at a corner, never cross.
struct OutlinePiece {
    std::vector<cv::Point2d> outer;
    std::vector<std::vector<cv::Point2d>> holes;
    double areaPx = 0; ///< the polygon's area = pixels of the piece
};

struct RegionOutline {
    std::int32_t id = 0;
    int side = 0; ///< the side map's value for this region's pixels (0 when no side map)
    std::int64_t pixels = 0;
    std::vector<OutlinePiece> pieces;
};

/// Outlines of every non-zero id of `labels` (CV_32S), split by `side` (CV_8U of the same size;
/// empty = one side). Pieces smaller than `minPiecePx` pixels are left out of `pieces` (still
/// counted in `pixels`). Ordered by id, then side.
std::vector<RegionOutline> regionOutlines(const cv::Mat& labels, const cv::Mat& side = {},
                                          int minPiecePx = 4);

} // namespace slicestation::pipeline
