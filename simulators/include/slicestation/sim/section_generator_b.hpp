#pragma once
/// The second generator family ("family B"): synthetic sections written apart from
/// generateSection (section_generator.hpp), with another renderer, other stains, another
/// deformation model and other damage models, so that a registration tuned on the first family
/// can be reported on sections it was not tuned on (issue 17).
///
/// What it models, from what real sections look like:
/// - every atlas id (the full Allen ids, not only major regions) gets its own stain level; ids
///   of one ontology group share part of it, the rest is drawn apart so neighbours often differ
///   strongly (immunostain), or the level follows a per-region cell density (Nissl), or the
///   contrast is mild with bright fibre tracts (autofluorescence), or the section is the Allen
///   average template plane (the regime intensity methods are made for);
/// - fibre tracts and ventricles follow their own rules (tracts dark or bright per stain,
///   ventricles empty like glass);
/// - texture: cell bodies as Gaussian blobs of about 12 um, Poisson-placed with a density that
///   varies by region, plus a mild low-frequency tissue density variation;
/// - scanner tiles with their own gain and gradient and visible seams, vignetting, optical blur,
///   shot and read noise; air bubbles under the coverslip (a dark rim, intact tissue inside);
/// - the map: a random affine (rotation, per-axis shrinkage/swelling, shear) and a smooth
///   non-linear field = a thin-plate spline through 16 randomly displaced control points, a
///   local swelling (isotropic expansion or shrinkage under a Gaussian window) and a scale
///   gradient along a random axis; checked to keep the Jacobian determinant above 0.5;
/// - damage: thin cracks (2-5 px at 1500 px wide, from an edge into the tissue), bites out of the
///   edge, free-floating fragments (cut off, moved and turned onto the glass), folds (a flap of
///   the edge folded back over the tissue: the edge moves in and the doubled band is brighter in
///   fluorescence, darker in brightfield);
/// - brightfield: RGB, tissue absorbs (darker than glass), DAB-brown for immunostains, cresyl
///   violet for Nissl, haematoxylin-like otherwise.
///
/// Units: pixels, pixel centres at integer coordinates, origin top-left; "image" is the generated
/// image, "atlas" the label plane given. Threading: re-entrant. Determinism: the output depends
/// only on the inputs; the same seed gives identical bytes on one build.

#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <string_view>
#include <vector>

namespace slicestation::sim {

enum class StainB {
    Immuno,           ///< per-id levels, strong contrast between neighbours
    Nissl,            ///< level follows a per-region cell density; texture dominated by cells
    Autofluorescence, ///< mild region contrast, fibre tracts bright
    Template,         ///< the Allen average template plane (GeneratorOptionsB::templatePlane)
};
std::string_view toString(StainB stain) noexcept;

/// Kinds of damage of this family. In GroundTruth::damage they appear as Crack -> Tear,
/// Bite -> Missing, Fragment -> Fragment, Fold -> Missing (the flap left its place).
enum class DamageKindB { Crack, Bite, Fragment, Fold };
std::string_view toString(DamageKindB kind) noexcept;

struct DamageOptionsB {
    bool crack = false;
    bool bite = false;
    bool fragment = false;
    bool fold = false;
    bool any() const { return crack || bite || fragment || fold; }
};

struct GeneratorOptionsB {
    std::uint64_t seed = 1;
    cv::Size imageSize{1500, 1100};   ///< each side in [300, 10000]
    double fillFraction = 0.7;        ///< tissue width / image width, roughly; in [0.2, 0.95]
    double maxRotationDeg = 25;       ///< uniform in [-max, max]; in [0, 180]
    double maxScaleJitter = 0.1;      ///< per-axis shrinkage/swelling (+/-); in [0, 0.4]
    double maxShear = 0.04;           ///< in [0, 0.4]
    double maxTranslationFrac = 0.05; ///< of image size; in [0, 0.4]
    double warpAmplitudeFrac = 0.008; ///< thin-plate control point displacement s.d. / tissue
                                      ///< width; in [0, 0.05]
    double swelling = 0.05;           ///< local and gradient scale change (+/-); in [0, 0.2]
    StainB stain = StainB::Immuno;
    bool brightfield = false; ///< RGB (CV_8UC3, BGR), tissue darker than glass
    double noise = 1.0;       ///< scales shot and read noise; in [0, 10]
    double texture = 1.0;     ///< scales cell and density texture; in [0, 3]
    bool tiles = true;        ///< scanner tiles (gain, gradient, seams)
    int bubbles = -1;         ///< air bubbles; -1 = 0 to 2 at random; in [-1, 20]
    int landmarkCount = 200;  ///< in [0, 100000]
    double atlasUmPerPx = 25; ///< atlas pixel size, sets the cell size; in [1, 200]
    DamageOptionsB damage;
    /// Template stain only: the average template on the atlas plane's grid (CV_32F, the size of
    /// the labels, any positive range; it is normalised by its 99.5th percentile in the brain).
    cv::Mat templatePlane;
    /// Used only when the ontology given is empty: ids rendered as fibre tracts / ventricles.
    /// With an ontology, every descendant of 1009 (fiber tracts) and 73 (ventricular systems) is.
    std::vector<std::int32_t> fiberTractIds{1009};
    std::vector<std::int32_t> ventricleIds{73};
    /// Labelled cells at known positions (GeneratedSectionB::cells); off by default.
    CellOptions cells;
};

struct GeneratedSectionB {
    cv::Mat image;     ///< CV_16UC1 (fluorescence) or CV_8UC3 BGR (brightfield)
    GroundTruth truth; ///< as for generateSection; damageMask 2 also marks a fold's doubled band
    std::vector<DamageKindB> damageKinds; ///< parallel to truth.damage
    double imageUmPerPx = 0;              ///< the mean true pixel size (atlasUmPerPx / scale)
    double minJacobian = 0;               ///< of the non-linear part of the true map
    /// The labelled cells painted (GeneratorOptionsB::cells); `counted`: in intact tissue.
    std::vector<TrueCell> cells;
};

/// Renders `atlasLabels` (CV_32S, 0 or negative outside the brain; full Allen ids or any ids)
/// as a microscope image of family B. `ontology` may be empty (see GeneratorOptionsB).
///
/// The true map is atlas = A (p + d(p)) for image pixel p, A the affine part
/// (truth.affineAtlasFromImage) and d the smooth field above. The tissue lies inside the image.
/// Blocking: CPU only, about a second at 1500 x 1100.
/// \return InvalidArgument when the labels are empty, not CV_32S or without a label > 0, when a
///         side of imageSize is outside [300, 10000], when an option is out of its range or not
///         finite, or when the Template stain has no templatePlane of the labels' size (CV_32F);
///         Internal when OpenCV fails unexpectedly.
[[nodiscard]] core::Result<GeneratedSectionB> generateSectionB(const cv::Mat& atlasLabels,
                                                               const core::Ontology& ontology,
                                                               const GeneratorOptionsB& options);

} // namespace slicestation::sim
