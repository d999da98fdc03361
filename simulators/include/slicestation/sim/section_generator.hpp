#pragma once
/// Synthetic microscope images of brain sections with exact ground truth.
///
/// An atlas label plane is deformed by a known map (random affine composed with a smooth
/// non-linear warp), rendered with a stain that is deliberately not a function of the atlas ids
/// alone (random per-region intensities, cell texture, gradients, uneven illumination, blur,
/// noise, slide debris), and optionally damaged (tear, missing chunk, moved fragment). The truth
/// holds the map for every pixel, landmarks in intact tissue, and masks of tissue and damage.
///
/// Units: all positions are pixels with pixel centres at integer coordinates and the origin at the
/// top-left pixel; "image" is the generated image, "atlas" the label plane given.
/// Threading: generateSection is re-entrant; it may use OpenCV's worker threads internally.
/// Determinism: the output depends only on the inputs; the same seed gives identical bytes.

#include "slicestation/core/result.hpp"
#include "slicestation/sim/section_cells.hpp"

#include <opencv2/core/mat.hpp>
#include <opencv2/core/matx.hpp>
#include <opencv2/core/types.hpp>

#include <cstdint>
#include <string_view>
#include <vector>

namespace slicestation::sim {

enum class Stain {
    Fluorescence, ///< DAPI-like: tissue bright on dark glass; CV_16UC1 output
    Brightfield,  ///< Nissl/H&E-like: pink-purple tissue on bright glass; CV_8UC3 (BGR) output
};

/// Kinds of damage to paint; each requested kind is painted once, at its own place.
struct DamageOptions {
    bool tear = false;     ///< a tapering crack from the boundary inwards, on one side
    bool missing = false;  ///< a chunk missing at the boundary
    bool fragment = false; ///< a boundary piece cut off and moved away from the rest
    // The damage models of issue 18, each off by default (a case asking for none of them keeps
    // its bytes). Painted after the three above, each on its own random stream.
    bool crack = false; ///< a thin crack, 1-5 px wide at 1500 px, crossing the tissue (glass)
    bool fold = false;  ///< a flap of the edge folded back: a band of doubled tissue, edge moved
    bool smallFragment = false; ///< a piece of 1-3% of the tissue cut off and moved away
    bool tornVentricle = false; ///< a ventricle's wall torn open: a wedge of glass out of it
    bool chatter = false;       ///< knife chatter: bands of alternating thickness across a patch
    bool any() const {
        return tear || missing || fragment || crack || fold || smallFragment || tornVentricle ||
               chatter;
    }
};

/// Anatomy that looks like damage and is not (issue 18): never in GroundTruth::damage.
struct AnatomyOptions {
    /// The ventricles grown by this share of the tissue width (0: as the atlas has them); an
    /// enlarged ventricle is glass where the atlas expects tissue. In [0, 0.05].
    double ventricleGrowthFrac = 0;
    /// A natural fissure opened: glass this wide (share of the tissue width) along the
    /// interface of two of `parts`, where they touch. 0: none. In [0, 0.03].
    double fissureOpenFrac = 0;
    /// Groups of atlas ids that lie apart across natural fissures (the defaults: cerebral
    /// cortex, brain stem without the hypothalamus, cerebellum, as collapsed Allen ids).
    std::vector<std::vector<std::int32_t>> parts{
        {315, 698, 1080, 822, 703}, {549, 958, 313, 771, 354}, {519, 528}};
};

struct GeneratorOptions {
    std::uint64_t seed = 1;
    cv::Size imageSize{1500, 1100};   ///< output image size in pixels, each side in [300, 10000]
    double fillFraction = 0.75;       ///< tissue width / image width, roughly; in [0.2, 0.95]
    double maxRotationDeg = 20;       ///< rotation uniform in [-max, max]; max in [0, 180]
    double maxAnisotropy = 0.08;      ///< per-axis scale jitter (+/-); in [0, 0.5]
    double maxShear = 0.05;           ///< shear jitter (+/-); in [0, 0.5]
    double maxTranslationFrac = 0.05; ///< of image size, as far as the tissue fits; in [0, 0.5]
    double warpAmplitudeFrac = 0.015; ///< peak non-linear displacement / tissue width; [0, 0.1]
    Stain stain = Stain::Fluorescence;
    double noise = 1.0;      ///< scales shot and read noise; in [0, 10]
    int landmarkCount = 200; ///< in [0, 100000]; fewer when the tissue is too small
    DamageOptions damage;
    AnatomyOptions anatomy;
    /// Labels rendered as fibre tracts (distinctly brighter or darker than their neighbours) and
    /// as ventricles (empty, like glass). The defaults are the Allen ids the built-in atlas and a
    /// collapsed Allen plane use.
    std::vector<std::int32_t> fiberTractIds{1009};
    std::vector<std::int32_t> ventricleIds{73};
    /// Labelled cells at known positions (GeneratedSection::cells); off by default.
    CellOptions cells;
};

/// Crack and torn ventricle appear as Tear, the small fragment as Fragment.
enum class DamageKind { Tear, Missing, Fragment, Fold, Chatter };
std::string_view toString(DamageKind kind) noexcept; ///< "tear", "missing", ...

struct DamageRegion {
    DamageKind kind;
    /// Outline of the tissue removed (tear, missing) or cut off (fragment: where the piece was
    /// before it moved), image px.
    std::vector<cv::Point2f> polygon;
    double areaPx = 0; ///< pixels of tissue removed or cut off
    /// Fragment only: where the piece went, original image position -> moved image position.
    /// Identity for the other kinds.
    cv::Matx23d motion{1, 0, 0, 0, 1, 0};
};

struct Landmark {
    cv::Point2d image; ///< image px; always a pixel centre (integer values)
    cv::Point2d atlas; ///< atlas px, the true map evaluated exactly at `image`
};

struct GroundTruth {
    /// CV_32F, image size: the true atlas coordinates of every image pixel (the map of the intact
    /// section; inside a moved fragment the tissue seen actually comes from elsewhere, see
    /// DamageRegion::motion). Defined everywhere, also outside the tissue.
    cv::Mat atlasX, atlasY;
    cv::Matx23d affineAtlasFromImage; ///< the affine part of the true map (image -> atlas)
    std::vector<Landmark> landmarks;  ///< inside intact tissue only (not in damage or fragment)
    cv::Mat tissueMask; ///< CV_8U 255 where tissue is present in the image (after damage;
                        ///< ventricles are not tissue)
    cv::Mat damageMask; ///< CV_8U: 0 none, 1 tear, 2 missing, 3 fragment (moved piece and the
                        ///< hole it left), 4 fold (the flap's place and the doubled band),
                        ///< 5 chatter
    std::vector<DamageRegion> damage;
    cv::Mat labelsInImage; ///< CV_32S atlas labels seen through the true map (before damage)
};

struct GeneratedSection {
    cv::Mat image; ///< CV_16UC1 (fluorescence) or CV_8UC3 BGR (brightfield)
    GroundTruth truth;
    /// The labelled cells painted (GeneratorOptions::cells), every one placed; `counted` tells
    /// which lie in intact tissue at the end.
    std::vector<TrueCell> cells;
};

/// Renders `atlasLabels` (CV_32S, 0 or negative outside the brain) as a microscope image.
///
/// The true map is atlas = q + d(q) with q = affineAtlasFromImage * image, where d is a sum of
/// Gaussian bumps small enough that the map is a diffeomorphism. The tissue lies fully inside
/// the image (the scale is reduced below fillFraction when a rotated section would not fit).
/// Blocking: CPU only, well under a second at 1500 x 1100.
/// \return InvalidArgument when the labels are empty, not CV_32S or have no label > 0, when a
///         side of imageSize is outside [300, 10000], or when an option is out of its range or
///         not finite; Internal when OpenCV fails unexpectedly.
[[nodiscard]] core::Result<GeneratedSection> generateSection(const cv::Mat& atlasLabels,
                                                             const GeneratorOptions& options);

} // namespace slicestation::sim
