#pragma once
/// Damage detection (paper Algorithm 2, section 3.2.2, and beyond it): torn, missing and
/// detached tissue, so a section can be re-mounted and its damage kept out of the matching.

#include <opencv2/core.hpp>

#include <string>
#include <string_view>
#include <vector>

namespace slicestation::pipeline {

enum class DamageKind { Tear, Missing, Fragment };
std::string_view toString(DamageKind kind) noexcept;

struct DamageRegion {
    DamageKind kind = DamageKind::Missing;
    std::vector<cv::Point2f> polygon; ///< outline, in the pixel frame of the masks it came from
    double areaPx = 0;                ///< in that frame
    double share = 0;                 ///< area / area of the section's tissue
    double lengthPx = 0;              ///< longest extent (a tear's depth)
    double openShare = 0;             ///< gaps: share of the rim on the glass outside the section
    double thicknessPx = 0;           ///< gaps: twice the largest inscribed radius
};

/// Lengths are fractions of the brain width (the OBB's major extent of the section), so the rule
/// means the same at every resolution; alpha in particular is a length, never a hop count.
struct DamageParams {
    double alphaFrac = 0.05;          ///< medial-axis pieces at least this long are deep concavities
    double symmetryRadiusFrac = 0.03; ///< how far a mirrored vertex may be from its partner
    double symmetryAngleDeg = 30;     ///< and how far its normal may turn
    double symmetricShare = 0.6;      ///< anatomy: at least this share of vertices has a partner
    double slackFrac = 0.006;         ///< registration slack removed from the tissue deficit
    double minRegionShare = 0.002;    ///< smaller regions are not reported
    double damagedShare = 0.008;      ///< decision: damage of at least this share of the tissue
    double deepTearFrac = 0.10;       ///< decision: or a tear at least this long
    double tearElongation = 3.0;      ///< length / mean width from which a gap is a tear
    double shallowFrac = 0.05;        ///< gaps along the outline thinner than this are slack
};

/// The outermost outline of the tissue as a polygon with unit normals (unoriented).
struct Outline {
    std::vector<cv::Point2f> points;
    std::vector<cv::Point2f> normals;
};

/// The largest outer contour of `tissueMask` (CV_8U), simplified to within 1 px, then resampled
/// so that no edge is longer than `maxSegmentPx`: the medial axis of a straight-sided wedge only
/// exists if its sides carry vertices.
Outline tissueOutline(const cv::Mat& tissueMask, double maxSegmentPx = 3.0);

/// The same resampling for any closed polygon.
std::vector<cv::Point2f> subdivide(const std::vector<cv::Point2f>& polygon, double maxSegmentPx);

/// A deep concavity of the outline found by the exterior medial axis.
struct Concavity {
    std::vector<cv::Point2f> points;  ///< outline vertices around the pocket
    std::vector<cv::Point2f> normals; ///< their unit normals (unoriented)
    double axisLength = 0;
    bool symmetric = false;           ///< a mirrored partner exists: anatomy
};

/// Algorithm 2, lines 1-4: the exterior medial axis of the outline, the pieces at least alpha
/// long, as concavities (symmetric = false).
std::vector<Concavity> deepConcavities(const Outline& outline, double alphaPx);

/// Algorithm 2, line 5: marks each concavity symmetric when at least `symmetricShare` of its
/// vertices, mirrored by `mirror` (image -> image, an involution across the brain's midline),
/// land within the radius of an outline vertex whose normal, mirrored, agrees.
void markSymmetric(std::vector<Concavity>& concavities, const Outline& outline,
                   const cv::Matx23d& mirror, double brainWidthPx, const DamageParams& params);

/// Where edges must not take part in the matching: around every asymmetric concavity (the
/// hull of its vertices grown by `marginPx`), CV_8U of `size`.
cv::Mat concavityExclusion(const std::vector<Concavity>& concavities, cv::Size size,
                           double marginPx);

/// Beyond the paper, after registration: gaps where the atlas (mapped into the image frame)
/// expects tissue but the section shows glass, anywhere in the section and symmetric or not
/// (`expectedTissue`: atlas brain minus ventricles; CV_8U), and tissue pieces lying mostly
/// outside the mapped atlas brain (`expectedBrain`) away from the main tissue (fragments).
/// `knownFragments` (CV_8U or empty): pieces already found detached (see extraPieces); a piece
/// mostly on them is a fragment wherever it lies.
std::vector<DamageRegion> tissueDamage(const cv::Mat& tissueMask, const cv::Mat& expectedTissue,
                                       const cv::Mat& expectedBrain, double brainWidthPx,
                                       const DamageParams& params,
                                       const cv::Mat& knownFragments = cv::Mat());

/// Tissue pieces beyond those the atlas has: when the section (CV_8U mask) has more pieces of at
/// least `minShare` of its largest than the atlas brain mask has, the smallest extra ones are
/// detached fragments. Returns their mask (empty image when there are none).
cv::Mat extraPieces(const cv::Mat& tissueMask, const cv::Mat& atlasMask, double minShare = 0.02);

/// The documented decision: damaged when the regions together cover at least damagedShare of the
/// tissue, or one tear is at least deepTearFrac of the brain width long.
bool isDamaged(const std::vector<DamageRegion>& regions, double brainWidthPx,
               const DamageParams& params);

/// A short human-readable summary ("tear 3.1%, missing 1.2% of the tissue" / "no damage").
std::string damageSummary(const std::vector<DamageRegion>& regions);

} // namespace slicestation::pipeline
