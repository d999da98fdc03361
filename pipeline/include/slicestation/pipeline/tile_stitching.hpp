#pragma once
/// Sections larger than the field of view are captured as overlapping tiles and stitched into
/// one section image.
///
/// Threading: pure functions, re-entrant. No I/O, no hardware.

#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"

#include <opencv2/core/mat.hpp>

#include <vector>

namespace slicestation::pipeline {

struct TilePlan {
    std::vector<hw::StagePosition> centres; ///< row-major: y rows top to bottom, x left to right
    int columns = 0;
    int rows = 0;
};

/// Tile centres covering a `widthUm` x `heightUm` region centred on `centre` with fields of
/// `fieldWidthUm` x `fieldHeightUm`, neighbours overlapping by at least `overlapFraction` of a
/// field (the spacing is spread evenly, so the overlap may be larger). One tile when the region
/// fits in the field. Every centre keeps `centre.zUm`.
/// \return the plan; an empty plan when a field size is not > 0, a region size is negative or
///         not finite, or overlapFraction is outside [0, 0.9].
TilePlan planTiles(const hw::StagePosition& centre, double widthUm, double heightUm,
                   double fieldWidthUm, double fieldHeightUm, double overlapFraction = 0.1);

struct Tile {
    cv::Mat image;           ///< every tile of one stitch has the same type
    hw::StagePosition stage; ///< stage position of the tile centre, µm
};

/// Stitches `tiles` into one image of the same type (8U, 16U or 32F; 1 to 4 channels).
///
/// Placement: by stage position (x right, y down, `umPerPx` µm per pixel). With
/// `refineWithPhaseCorrelation`, the offset of every pair of tiles overlapping by at least 16 px
/// each way is measured by phase correlation on the overlap (Kuglin & Hines 1975; OpenCV
/// phaseCorrelate with a Hann window) and accepted when the peak is clear (response >= 0.1) and
/// the shift is bounded (at most a quarter of the overlap's smaller side, and at least 2 px is
/// always allowed); all tile positions are then solved together by least squares from the
/// accepted offsets, weakly tied to the stage positions (so tiles over blank glass keep their
/// stage placement). Positions are rounded to whole pixels relative to the first tile.
/// Blending: in overlaps, each tile is weighted by its distance to its own border (a linear
/// cross-fade), so there are no seams; pixels covered by no tile are 0.
/// Memory: about 4 x (channels + 1) bytes per mosaic pixel while stitching.
///
/// \return the mosaic (its top-left pixel is the top-left of the leftmost/topmost tile);
///         InvalidArgument (no tiles, an empty tile, tiles of different types, an unsupported
///         type, umPerPx not > 0, a non-finite stage position, a mosaic above 40000 px a side).
[[nodiscard]] core::Result<cv::Mat> stitchTiles(const std::vector<Tile>& tiles, double umPerPx,
                                                bool refineWithPhaseCorrelation = true);

} // namespace slicestation::pipeline
