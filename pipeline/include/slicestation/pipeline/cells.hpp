#pragma once
/// Cells per region (issue 22, the paper's application, section 4 "Neuron counting"): a cell
/// detector on one channel of a section image, and the count of the detected cells in every
/// region of the atlas mapped onto the section by a Registration, rolled up the ontology to
/// every ancestor, with the region areas; damaged tissue is left out of both.
///
/// Units: section pixels (full resolution, pixel centres at integers, origin top-left); areas in
/// section pixels (the caller turns them into mm^2 with the section's pixel size).
/// Threading: re-entrant; OpenCV may use its worker threads. No I/O.

#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <string_view>
#include <vector>

namespace slicestation::pipeline {

/// Whether cells are brighter than their surroundings (fluorescence) or darker (brightfield:
/// stained cells absorb). Auto decides from the image: glass brighter than tissue = Dark.
enum class CellPolarity { Auto, Bright, Dark };
std::string_view toString(CellPolarity polarity) noexcept;

enum class CellMethod {
    /// Scale-normalised Laplacian of Gaussian at the cell size on the locally
    /// background-subtracted plane (white top-hat), local maxima (non-maximum suppression over
    /// the cell's own disc) above a multiple of the response's local robust noise, answering
    /// 1.7 times more at the cell's scale than at half of it (smaller texture is not a cell).
    /// Touching cells closer than about 1.1 diameters give one maximum: blobs larger than one
    /// cell are split by area (CellDetectorOptions::splitAt). In 8- and 16-bit images, cells
    /// clipped at the format's ceiling are found by their clipped core and shoulder (a disc of
    /// d/3 at the ceiling, 0.68 of the headroom at d/2; docs/cells.md "Nissl sections").
    LoG,
    /// The paper's rule: threshold the background-subtracted plane, drop clusters under
    /// minClusterPx, count each cluster as round(area / median cluster area) cells at its
    /// centroid. Kept to compare against (slst_bench_cells prints both).
    Threshold,
};
std::string_view toString(CellMethod method) noexcept;

struct CellDetectorOptions {
    /// Which plane of a multi-channel image, in the file's order (0 = red of an RGB image, as
    /// libraries other than OpenCV count); -1 = the grey of all channels. A one-channel image
    /// has only channel 0 (or -1).
    int channel = -1;
    double diameterPx = 6; ///< typical cell body diameter, section px; in [2, 200]
    CellPolarity polarity = CellPolarity::Auto;
    CellMethod method = CellMethod::LoG;
    /// A detection's response must exceed this many robust standard deviations (1.4826 x the
    /// median absolute deviation) of the method's response. LoG: of the LoG response, measured
    /// locally (tiles of 10 diameters, interpolated); Threshold: of the background-subtracted
    /// plane over all searched pixels. 4 was chosen on generated family 1 (slst_bench_cells).
    double minSnr = 4;
    /// Two maxima closer than this x diameterPx are one cell (LoG only).
    double minSeparation = 0.6;
    /// LoG only: touching cells that gave one maximum are split by area. Each detection's blob
    /// is the connected set of pixels above half the brightest pixel near them (a cell's
    /// half-maximum outline); a blob of k detections whose area is n >= k + 1 times the median
    /// area of one-detection blobs (rounded at splitAt - 1 above an integer) holds n cells,
    /// placed by k-means over its pixels. 0 = no splitting.
    double splitAt = 1.5;
    int minClusterPx = 5; ///< Threshold only: smaller clusters are noise (the paper's 5 px)
    /// CV_8U of the image's size, non-zero = search here (e.g. the tissue). Empty = everywhere.
    cv::Mat mask;
};

struct DetectedCell {
    cv::Point2d imagePx;  ///< centre, section px (sub-pixel)
    double response = 0;  ///< in robust noise units (the SNR of the detection)
    int clusterCells = 1; ///< Threshold: cells counted at this centroid (>= 1); LoG: 1
};

/// Detects cells in `image` (CV_8U/CV_16U/CV_32F, 1, 3 or 4 channels; colour in OpenCV's BGR(A)
/// order as core::readImage returns it).
/// \return InvalidArgument (empty or unsupported image, channel not in the image, diameter or
///         minSnr out of range, mask of another size or type); Internal (OpenCV failed).
[[nodiscard]] core::Result<std::vector<DetectedCell>>
detectCells(const cv::Mat& image, const CellDetectorOptions& options = {});

/// A cell placed in the atlas.
struct MappedCell {
    cv::Point2d imagePx;
    cv::Point2d atlasPx;      ///< through the registration (affine + warp)
    std::int32_t atlasId = 0; ///< label at atlasPx (nearest), 0 = outside the brain
    bool excluded = false;    ///< in damaged tissue (Registration::damage): not counted
    int cells = 1;            ///< DetectedCell::clusterCells
};

/// One row of the table: a region and its totals including all its descendants.
struct RegionCount {
    std::uint32_t id = 0;
    std::uint32_t parentId = 0; ///< 0 for the root or when unknown to the ontology
    int depth = 0;              ///< 0 = root; ids the ontology lacks: 0
    std::int64_t cells = 0;
    double areaPx = 0; ///< intact tissue of the region seen in the section, section px
};

struct CellTable {
    std::vector<MappedCell> cells; ///< every detection, in detection order
    /// Regions with tissue or cells in the section, each with every ancestor of the ontology
    /// (counts and areas summed over descendants); in the ontology's file order, then ids it
    /// lacks in increasing order.
    std::vector<RegionCount> regions;
    double tissueAreaPx = 0;   ///< intact tissue in the brain, section px
    double excludedAreaPx = 0; ///< tissue inside damage, left out of every area
    std::int64_t excludedCells = 0;
};

/// Maps `cells` through `registration` onto `atlasLabels` (the labels registered to, CV_32S) and
/// counts them per region. Areas: the section's tissue (Registration::workingTissueMask) with
/// the atlas labels warped onto it, at working resolution scaled to section px. Damage: the
/// Registration::damage polygons (section px), excluded from counts and areas. `ontology` may be
/// empty: each id is then its own root (no roll-up).
/// \return InvalidArgument (labels empty or not CV_32S, a registration without working data).
[[nodiscard]] core::Result<CellTable> countCells(const Registration& registration,
                                                 const cv::Mat& atlasLabels,
                                                 const std::vector<DetectedCell>& cells,
                                                 const core::Ontology& ontology);

/// Sums a table of leaf regions (id -> cells, area) up the ontology (used by countCells; public
/// for tests and for per-run totals). Rows as in CellTable::regions.
std::vector<RegionCount> rollUp(const std::vector<RegionCount>& leaves,
                                const core::Ontology& ontology);

} // namespace slicestation::pipeline
