#pragma once
/// Damage detection (paper Algorithm 2, section 3.2.2, and beyond it): torn, missing and
/// detached tissue, so a section can be re-mounted and its damage kept out of the matching.

#include <opencv2/core.hpp>

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace slicestation::pipeline {

enum class DamageKind { Tear, Missing, Fragment, Fold, Chatter };
std::string_view toString(DamageKind kind) noexcept;

/// What a section is, for the technician: clean; damaged (re-mount it); or "check the
/// registration": tissue looks missing only where the atlas cannot be trusted locally, so the
/// deficit may be the registration's misfit rather than a tear.
enum class DamageVerdict { Clean, Damaged, CheckRegistration };
std::string_view
toString(DamageVerdict verdict) noexcept; ///< "clean", "damaged", "check_registration"

struct DamageRegion {
    DamageKind kind = DamageKind::Missing;
    std::vector<cv::Point2f> polygon; ///< outline, in the pixel frame of the masks it came from
    double areaPx = 0;                ///< in that frame
    double share = 0;                 ///< area / area of the section's tissue
    double lengthPx = 0;              ///< longest extent (a tear's depth)
    double openShare = 0;             ///< gaps: share of the rim on the glass outside the section
    /// Gaps: a band along a ventricle's lumen (over DamageParams::alongOutlineShare of the rim on
    /// the glass the section shows in the mapped ventricle, within the slack, and at least
    /// bandElongation times longer than thick): the ventricle's wall lying farther out than the
    /// atlas's (dropAlongMidline leaves such bands out where they reach the midline; the series
    /// context counts the earlier sections' glass at their place, judgeInSeries).
    bool alongVentricle = false;
    double thicknessPx = 0; ///< gaps: twice the largest inscribed radius
    /// Gaps, where the grey image is known: the median grey level inside the gap above the
    /// glass outside the section, as a share of the span from the glass to the median tissue
    /// (0 = glass, 1 = typical tissue), and in units of the glass noise (robust spread of the
    /// glass outside the section).
    double levelShare = 0;
    double levelNoiseUnits = 0;
    /// How sure the region is damage, in [0, 1]: 0.5 where its evidence alone reaches the
    /// decision line (damageScore).
    double score = 0;
    /// Series context (damage_series.hpp): the share of the run's already registered
    /// neighbours showing damage at the same atlas place, in [0, 1]. Anatomy persists over
    /// neighbouring sections, a tear does not: the evidence is scaled by (1 - persistence).
    double persistence = 0;
    /// The outline in atlas px through the map the damage check judged against, when that is
    /// not the registration's own (RegistrationOptions::damageWithoutSmooth); empty otherwise.
    std::vector<cv::Point2f> atlasOutline;
    /// Gaps: within half the gap's length around it, the section's tissue lying where the
    /// mapped atlas expects none (outside its brain, or in a ventricle) over the glass lying
    /// where it expects tissue (at least the gap's own area), both as they are, without slack.
    /// A structure of the atlas placed wrong moves as much area each way (about 1: a crescent
    /// of glass on one side, one of tissue on the other); lost tissue leaves only the glass
    /// (about 0, what slack along a boundary that fits shows).
    double excessShare = 0;
    double excessVentricleShare = 0; ///< the part of excessShare lying in mapped ventricles
    /// The atlas cannot be trusted around this gap (excessShare >= DamageParams::misfitExcess):
    /// the gap may be the registration's misfit, not lost tissue (decideDamage).
    bool misfit = false;
    /// Gaps: mirroredShare of the section's glass; fragments: of the section's tissue (-1
    /// undecided, 0 not measured). At least DamageParams::mirroredGap: a twin on the other side,
    /// anatomy (left out of the regions when DamageParams::leaveOutMirroredGaps).
    double mirrorShare = 0;
    /// Found by thinCracks: a line of glass (or of a valley as deep as a crack's) no wider than
    /// DamageParams::crackMaxWidthPx with tissue on both sides. A boundary placed wrong cannot
    /// leave such a line; only a thin gap of the atlas (a fissure, a narrow ventricle) placed
    /// wrong can (markMisfit).
    bool crack = false;
    /// Found against the ICP affine alone, where the final map left no gap: a piece lost from
    /// the edge whose cut the outline pull and the warps bent the atlas onto
    /// (DamageParams::followedBites; its mirror and misfit are judged under the affine too).
    bool followed = false;
    /// A gap along the outline the slack or band rule (DamageParams::shallowFrac,
    /// bandElongation) would have left out, kept because it lies at a cut: a deep asymmetric
    /// concavity of the section's own outline (DamageParams::bitesAtCuts). Always Missing, its
    /// area taken up to the expected outline (the slack band was lost with it).
    bool atCut = false;
};

/// A gap: glass where the atlas expects tissue (Tear, Missing), not a piece, a fold or chatter.
bool isGap(const DamageRegion& d);

/// Lengths are fractions of the brain width (the OBB's major extent of the section), so the rule
/// means the same at every resolution; alpha in particular is a length, never a hop count.
struct DamageParams {
    double alphaFrac = 0.05; ///< medial-axis pieces at least this long are deep concavities
    double symmetryRadiusFrac = 0.03; ///< how far a mirrored vertex may be from its partner
    double symmetryAngleDeg = 30;     ///< and how far its normal may turn
    double symmetricShare = 0.6;      ///< anatomy: at least this share of vertices has a partner
    double slackFrac = 0.006;         ///< registration slack removed from the tissue deficit
    double minRegionShare = 0.002;    ///< smaller regions are not reported
    double damagedShare = 0.008;      ///< decision: damage of at least this share of the tissue
    double deepTearFrac = 0.10;       ///< decision: or a tear at least this long
    double crackElongation = 3.0;     ///< and at least this many times its thickest width
    /// A crack's end under a pixel wide shows as a dark line (darkValleys): below this share of
    /// the way from the glass to the median tissue level,
    double threadDarkness = 0.4;
    /// and a valley at least this share of that span deeper than the tissue on both sides.
    double threadDepth = 0.25;
    double tearElongation = 3.0;    ///< length / mean width from which a gap is a tear
    double alongOutlineShare = 0.3; ///< a gap with more of its rim on the outside glass lies
                                    ///< along the outline
    double shallowFrac = 0.05;      ///< gaps along the outline thinner than this are slack
    double bandElongation = 5.0;    ///< gaps along the outline this much longer than thick
                                    ///< are an outline that did not fit, not a bite
    double fissureRingFrac = 0.03;  ///< how far around a gap the parts beside it are looked for
    double fissurePurity = 0.6;     ///< share of one part on a side for that side to be it
    /// A gap whose median grey level lies more than this many glass-noise units above the glass
    /// is dim tissue (a pale tract), not glass showing through: not damage. 3 = the usual
    /// three-sigma of a single pixel, generous to glass since a gap's median is far steadier.
    double glassNoiseUnits = 3.0;
    /// Cracks (thinCracks): glass lines at most this wide (full-resolution px; 1-5 px at
    /// 1500 px is what a section's crack is),
    double crackMaxWidthPx = 7.0;
    /// and at least this share of the brain width long.
    double crackMinFrac = 0.05;
    /// The crack pass works on the section reduced to at most this longer side (px). The crack
    /// widths above are pixels of a section of about 1500 px; a larger image shows a crack wider
    /// in pixels, and at 8000 px the full-resolution pass took 8 s of a 10 s registration.
    /// 2048 leaves sections up to 2048 px (the benchmarks' 1500 x 1100) at full resolution.
    int crackMaxSidePx = 2048;
    /// A crack narrower than the blur shows no glass: its pixels are also those of a dark
    /// valley (darkValleys with threadDepth) below this share of the way from the glass to the
    /// median tissue. 0: glass only. On since 2026-12-02 (docs/damage.md, "The crack valleys
    /// on"): the daemon test's false cracks were a dark atlas tract, see AtlasExpectation::dark.
    double crackDarkness = 0.4;
    /// The dark pixels (below crackDarkness) that are not glass and touch a crack are its
    /// blurred flanks: at most this many times its area. More is the narrow end of a dim
    /// structure (a dark fibre tract), not a crack.
    double crackDimBody = 3.0;
    /// ... unless the line is a valley in those pieces: its core (the darker quarter of its
    /// pixels) at least this share of the way from their level (their median beside it) down
    /// to the glass. A crack crossing a dim region shows the glass through it; a dim
    /// structure's thin end is at the structure's own level. 0: every line touching a large
    /// dim body is that body.
    double crackBelowBody = 0.5;
    /// Beside a crack lies tissue: at most this share of glass-level pixels there. Dim textured
    /// tissue has glass-level grains between its cells, whose thin glass webs are no crack.
    double crackWallGlass = 0.02;
    /// A crack followed across a break (continueTears): where a crack narrows (at a bend, or
    /// closing up) it shows only as a shallow line, neither glass nor a thread, and what shows
    /// beyond is a piece too short to be a crack alone. A piece passing every crack test but
    /// the length, at least this share of the brain width long (half crackMinFrac: half the
    /// shortest crack), continues a tear when the break between them is at most crackMinFrac of
    /// the width and is bridged by pixels darker than the tissue around it by threadDepth of
    /// the span from glass to tissue (a valley as deep as a thread's). Not fitted
    /// (docs/damage.md, "A crack followed where it narrows"). 0: no piece is collected.
    double crackPieceFrac = 0.025;
    /// Knife chatter (chatterBands): the thickness swinging in parallel bands. A tile's
    /// strongest period within these fractions of the brain width (the generator's chatter has
    /// 1-2.5%, here with margin both ways; a real knife's period depends on its speed and how it
    /// vibrates, and one much finer than 0.8% of a mouse brain, under some 80 um, is not looked
    /// for),
    std::array<double, 2> chatterPeriodFrac{0.008, 0.03};
    /// its swing at least this (0.1: the thickness 10% above and below its mean; the level is
    /// relative to a Gaussian mean over chatterLevelFrac of the width, tiles chatterTileFrac wide),
    double chatterSwing = 0.1;
    double chatterLevelFrac = 0.03;
    double chatterTileFrac = 0.12;
    /// and at least this many such tiles (overlapping by half) sharing the one frequency, 0: off;
    int chatterTiles = 8;
    /// and they at least this share of all the tiles that swing as much: the knife has one
    /// period and direction, tissue's texture at the same scale scatters over every direction.
    double chatterDominance = 0.5;
    /// Folds (foldBands): the band along the edge at least this many times as far above the
    /// glass as the same region behind it; 2 is tissue doubled, 1 none, 1.5 half way.
    double foldRatio = 1.5;
    /// Folds: the band that would hold a flap folded about the crease (a line fitted where the
    /// gap meets the tissue), as deep as the gap reaches beyond that line, along the gap's
    /// stretch, against the tissue behind and beside it; off: a band as deep as the gap all
    /// round it against the band behind that (the first version).
    bool foldFromCrease = true;
    /// A gap with at least this much misplaced tissue beside it (DamageRegion::excessShare) is
    /// a misfit: a boundary shifted leaves as much tissue where the atlas expects glass as glass
    /// where it expects tissue (share 1); lost tissue leaves none (0). 0.5: half way, not tuned.
    double misfitExcess = 0.5;
    /// Bilateral anatomy (mirroredShare): a gap whose mirror image across the brain's midline
    /// shows glass in the section over at least this share of it has a mirrored twin: an
    /// enlarged ventricle (both sides), a cleft anatomy has on both sides, or tissue the atlas
    /// plane has and the section lacks on both sides (the plane or the fit, not a tear). Damage
    /// is one-sided. The same for a piece lying apart whose mirror image is tissue (the cortex
    /// apart from the brain stem on both sides, caudally); a piece broken off has no twin.
    /// 0.5: half way between no twin (0) and a full twin (1), not tuned.
    double mirroredGap = 0.5;
    /// Leave such gaps out. On since 2026-12-03, when the torn gerbi 14 kept its flag without
    /// its bilateral ventricle gaps (crackPieceFrac; docs/damage.md, "Bilateral anatomy" and "A
    /// crack followed where it narrows").
    bool leaveOutMirroredGaps = true;
    /// Also look for gaps along the outline (over alongOutlineShare of their rim on the outside
    /// glass, with the gap rules' own depth and shape limits) against the ICP affine alone, and
    /// report those the final map closed (DamageRegion::followed). The outline pull and the
    /// warps follow the section's outline, a cut edge included, so a bite leaves no gap against
    /// the final map; the affine, fitted with the deep concavities left out (paper Algorithm 2),
    /// cannot bend into it (docs/damage.md, "Bites the warp followed").
    bool followedBites = true;
    /// Bites at a cut: where the section's own outline is a deep asymmetric concavity (paper
    /// Algorithm 2's damage candidates, given to tissueDamage as `cutOutline`), a gap along the
    /// outline is lost tissue however shallow or long: the slack (shallowFrac) and band
    /// (bandElongation) rules, for an outline that is faint or did not fit, do not apply there
    /// (DamageRegion::atCut; docs/damage.md, "Bites at a cut").
    bool bitesAtCuts = true;
    /// The section is flagged when its damage score reaches this (a station setting; 0.5 is the
    /// documented decision line of damagedShare and deepTearFrac).
    double flagScore = 0.5;
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
    bool symmetric = false; ///< a mirrored partner exists: anatomy
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

/// What the registered atlas expects in the section frame: CV_8U masks of the tissue mask's size.
struct AtlasExpectation {
    cv::Mat tissue; ///< the atlas brain minus ventricles
    cv::Mat brain;  ///< the atlas brain
    /// The parts of the brain that lie apart across natural fissures (such as the cerebrum and
    /// the brain stem), numbered 1.. (0 = none; see partMap), or empty. Sectioning often opens
    /// those fissures.
    cv::Mat parts;
    /// The mapped atlas regions the section itself shows dark (darkAtlasRegions: a fibre tract
    /// unstained at the glass level), or empty. A dark line inside one is that region, no crack.
    cv::Mat dark = cv::Mat();
};

/// The brain's midline in a section's pixels, as two points on it (equal = unknown). The
/// longitudinal fissure (and the cleft between the olfactory bulbs) runs along it.
struct Midline {
    cv::Point2f a, b;
};

/// A region's polygon (in its frame's pixels) in pixels of a frame `scale` times as fine (the
/// pixel centres kept: (p + 0.5) scale - 0.5, as cv::resize aligns them), rounded.
std::vector<cv::Point> pixelPolygon(const std::vector<cv::Point2f>& polygon, double scale);

/// `poly` (at least 3 points) filled in a mask (CV_8U) of `box`'s size, `box` giving the mask's
/// place in the polygon's frame.
cv::Mat polygonMask(const std::vector<cv::Point>& poly, cv::Rect box);

/// Removes the gaps (Tear, Missing; polygons in the midline's pixels) no thicker than
/// `maxThicknessPx` (a crack's width) lying along the midline: at least 70% of the gap within
/// `ringPx` of it and its principal axis within 20 degrees of it, as thinCracks leaves out
/// lines there. A slit on the midline is the longitudinal fissure (or the third ventricle)
/// opened, and its mirror image is itself, so the mirror test cannot judge it; a wider gap (a
/// ventricle torn open along the midline) is judged as any other. Also removes, whatever their
/// thickness, the bands along a ventricle's lumen (DamageRegion::alongVentricle) that reach
/// within `ringPx` of the midline: the midline's ventricles (the third, the lateral ones beside
/// the septum) wider than the atlas's, each its own mirror image; and the bites kept at a cut
/// (DamageRegion::atCut) that reach that ring: a notch on the midline is the cleft between the
/// hemispheres, as for followedGaps. Nothing is removed when the midline is unknown (a == b).
void dropAlongMidline(std::vector<DamageRegion>& regions, const Midline& midline, double ringPx,
                      double maxThicknessPx);

/// Beyond the paper, after registration: gaps where the atlas expects tissue but the section
/// shows glass, anywhere in the section and symmetric or not, and tissue pieces lying mostly
/// outside the mapped atlas brain away from the main tissue (fragments). A gap with one of
/// `expected.parts` on one side and another on the other is a fissure opened, and a long band
/// along the outline is an outline that did not fit: neither is damage.
/// `knownFragments` (CV_8U or empty): pieces already found detached (see extraPieces); a piece
/// mostly on them is a fragment wherever it lies. `grey` (CV_32F, tissue bright, or empty): the
/// section, for the thin dark end of a crack (darkValleys), which counts to a tear's length.
/// `cutOutline` (CV_8U or empty): where the section's outline is a deep asymmetric concavity
/// (concavityExclusion); a gap at least half on it is a bite however shallow
/// (DamageParams::bitesAtCuts).
std::vector<DamageRegion> tissueDamage(const cv::Mat& tissueMask, const AtlasExpectation& expected,
                                       double brainWidthPx, const DamageParams& params,
                                       const cv::Mat& knownFragments = cv::Mat(),
                                       const cv::Mat& grey = cv::Mat(),
                                       const cv::Mat& cutOutline = cv::Mat());

/// Bites the final map followed (DamageParams::followedBites): of `againstAffine` (tissueDamage
/// against the ICP affine alone), the gaps (Tear, Missing) along the outline, over
/// params.alongOutlineShare of their rim on the outside glass, that reach a deep asymmetric
/// concavity of the section's outline (`damagedOutline`, concavityExclusion: the paper's damage
/// candidates, CV_8U), that the midline does not cross (a notch there is the cleft between the
/// hemispheres, as deep as the brain was pressed together) and that share at most a tenth of
/// their area with a gap of `found` (tissueDamage against the final map; all in the pixels of
/// `damagedOutline`), marked DamageRegion::followed. Empty when params.followedBites is off or
/// `damagedOutline` is empty.
std::vector<DamageRegion> followedGaps(std::vector<DamageRegion> againstAffine,
                                       const std::vector<DamageRegion>& found,
                                       const cv::Mat& damagedOutline, const Midline& midline,
                                       double midlineRingPx, const DamageParams& params);

/// Thin cracks at full resolution: lines of glass a few pixels wide crossing the tissue, where
/// the section split and the slide shows through. A pixel is glass when its lightly blurred
/// (0.7 px) level lies within params.glassNoiseUnits of the glass noise above the glass outside
/// the section (both measured on `grey`), or when it lies in a dark valley as wide as a crack
/// (darkValleys below params.crackDarkness, disc crackMaxWidthPx + 2: a crack narrower than the
/// optics' blur never reaches the glass level); a crack is such pixels that a closing of the
/// rest by a disc of params.crackMaxWidthPx fills (narrower than that, tissue on both sides),
/// at least params.crackMinFrac of the brain width long and crackElongation times longer than
/// wide, inside the mapped atlas brain, not beside a mapped ventricle (within slackFrac of the
/// width; a ventricle's slit is glass too), not between two of `expected.parts` and not along
/// the midline (within fissureRingFrac of it, 20 degrees; both are natural fissures), with
/// tissue, not more glass, beside it (at most crackWallGlass of the pixels 2 to crackMaxWidthPx
/// + 2 px away), and not mostly (over half) inside `expected.dark` grown by the slack (a mapped
/// region the section shows dark, darkAtlasRegions).
/// `grey`: CV_32F, tissue bright, full resolution; `tissue`: the section's tissue mask at that
/// size; `expected` and `ventricles` (CV_8U) the mapped atlas at that size. Returned regions are
/// tears in those pixels, `share` of the tissue's area, skipping those overlapping `known`
/// (CV_8U gaps already found, or empty) by half their area. `pieces` (or null): receives the
/// lines that pass every test but the length, at least params.crackPieceFrac of the brain width
/// long (for continueTears).
std::vector<DamageRegion> thinCracks(const cv::Mat& grey, const cv::Mat& tissue,
                                     const AtlasExpectation& expected, const cv::Mat& ventricles,
                                     double brainWidthPx, const DamageParams& params,
                                     const Midline& midline, const cv::Mat& known = cv::Mat(),
                                     std::vector<DamageRegion>* pieces = nullptr);

/// A crack followed across breaks (DamageParams::crackPieceFrac): each tear of `regions` (kind
/// Tear) is joined by the `pieces` (thinCracks) whose break to its outline, or to a piece
/// already joined to it, is a fainter stretch of the crack (at most crackMinFrac of
/// `brainWidthPx` long, and bridged, in a box around it as wide as it is long each way, by
/// pixels of `tissue`, holes filled, darker in `grey` than the median of the box's other tissue
/// by threadDepth of the span from the glass to the tissue); each piece joins one tear at most,
/// and the tear's lengthPx grows by theirs. `grey` (CV_32F, tissue bright) and `tissue` (CV_8U)
/// are in mask px, `polygonScale` times finer than the regions' frame (polygon px x
/// polygonScale = mask px); `brainWidthPx` in mask px. Returns the pieces joined to some tear
/// (to be reported with it); the others are dropped.
std::vector<DamageRegion> continueTears(std::vector<DamageRegion>& regions,
                                        const std::vector<DamageRegion>& pieces,
                                        const cv::Mat& grey, const cv::Mat& tissue,
                                        double brainWidthPx, const DamageParams& params,
                                        double polygonScale = 1.0);

/// Folds: a flap of the edge folded back over the tissue. The edge moves in (the atlas expects
/// tissue where glass now is, along the outline) and the tissue beside it is doubled: within one
/// atlas region, the band inside the crease (a straight line fitted where the gap meets the
/// tissue), as deep as the gap reaches beyond it and along the gap's stretch, is about twice as
/// far above the glass as the tissue behind and beside it (fluorescence adds; absorbance adds in
/// brightfield, inverted, less than twice). params.foldFromCrease false: the band as deep as the
/// gap all round it against the band behind that. For each gap along the outline (over
/// alongOutlineShare of its rim on the outside glass), at least crackMinFrac of the brain width
/// long, the ratio is taken per atlas region (`labels`, CV_32S, the mapped atlas) over the two
/// bands and combined by pixel count; a fold when it reaches params.foldRatio. Returns the doubled
/// bands as Fold regions (working px of the masks given). `expectedTissue`: the mapped atlas brain
/// minus ventricles (CV_8U).
std::vector<DamageRegion> foldBands(const cv::Mat& grey, const cv::Mat& tissueMask,
                                    const cv::Mat& expectedTissue, const cv::Mat& labels,
                                    double brainWidthPx, const DamageParams& params);

/// The glass level (mean outside `tissueMask`) and the typical tissue level (median inside) of a
/// section's grey image (CV_32F, tissue bright); both 0 when the mask is empty or full.
struct GreyLevels {
    float glass = 0;
    float tissue = 0;
};
GreyLevels greyLevels(const cv::Mat& grey, const cv::Mat& tissueMask);

/// Thin dark lines in tissue: pixels of `grey` (CV_32F, tissue bright, the whole section or a
/// part) lightly blurred (0.7 px) below params.threadDarkness of the way from the glass to the
/// tissue level, in a valley (black top-hat, `discPx` disc) at least params.threadDepth of that
/// span deep. A crack narrower than a pixel is such a line; dim tissue and its edge against
/// bright tissue are not. CV_8U.
/// `discPx`: the closing disc of the top-hat (a valley narrower than it counts).
cv::Mat darkValleys(const cv::Mat& grey, GreyLevels levels, const DamageParams& params,
                    int discPx = 5);

/// The mapped atlas regions (`labels`, CV_32S, 0 = none) whose median level in `grey` (CV_32F,
/// tissue bright) over the pixels of `valid` (CV_8U) lies below `darkness` of the way from
/// `levels.glass` to `levels.tissue`: anatomy that is itself dark (an unstained tract), where a
/// dark line is that region's own, not glass showing through. CV_8U of the labels' size.
cv::Mat darkAtlasRegions(const cv::Mat& grey, const cv::Mat& labels, const cv::Mat& valid,
                         GreyLevels levels, double darkness);

/// The part of each pixel of `labels` (CV_32S atlas ids): 1 + the index of the group in `parts`
/// holding its id, 0 for ids in none. CV_8U.
cv::Mat partMap(const cv::Mat& labels, const std::vector<std::vector<std::int32_t>>& parts);

/// Whether a gap (`region`, CV_8U) lies between two parts: split the pixels within `ringPx`
/// around it by its principal axis; on each side at least a quarter of them must carry a part
/// (`parts`, CV_8U as from partMap, 0 where there is no tissue), at least `purity` of those
/// one part, and the two sides' parts must differ. A tear through one part, or across an
/// interface, has the same part, or a mix, on both sides; a bite out of the edge has glass on
/// one.
bool betweenParts(const cv::Mat& region, const cv::Mat& parts, int ringPx, double purity);

/// Tissue pieces beyond those the atlas has: when the section (CV_8U mask) has more pieces of at
/// least `minShare` of its largest than the atlas brain mask has, the smallest extra ones are
/// detached fragments. Returns their mask (empty image when there are none).
cv::Mat extraPieces(const cv::Mat& tissueMask, const cv::Mat& atlasMask, double minShare = 0.02);

/// The thin threads of a gap mask that an opening removed (`rawGaps` without `openedGaps`, both
/// CV_8U, same size; rawGaps may hold dark lines too), labelled 8-connected as by
/// cv::connectedComponentsWithStats.
struct GapThreads {
    cv::Mat labels; ///< CV_32S
    cv::Mat stats;  ///< CC_STAT_* per label
};
GapThreads gapThreads(const cv::Mat& rawGaps, const cv::Mat& openedGaps);

/// The length (longest side of the smallest rotated rectangle) of a gap `region` (CV_8U) with
/// the threads touching it: a crack's tapering end, which the opening cut off, counts.
double crackLength(const cv::Mat& region, const GapThreads& threads);

/// The pieces (8-connected) of `pieces` (CV_8U) with at least `share` of their area inside
/// `region` (CV_8U, same size).
cv::Mat piecesInside(const cv::Mat& pieces, const cv::Mat& region, double share);

/// The evidence of one region (1 at the decision line): its share of the tissue over
/// damagedShare, or for a crack (a tear at least crackElongation times longer than its thickest
/// width, DamageRegion::thicknessPx) its length over deepTearFrac of the brain width; times
/// (1 - DamageRegion::persistence).
double damageEvidence(const DamageRegion& region, double brainWidthPx, const DamageParams& params);

/// Evidence e mapped to a score in [0, 1): 1 - 2^-e (0.5 at e = 1).
double scoreFromEvidence(double evidence);

/// Sets every region's score and returns the section's: the score of the larger of the regions'
/// summed share (each times 1 - persistence) over damagedShare and the strongest crack's
/// evidence.
double damageScore(std::vector<DamageRegion>& regions, double brainWidthPx,
                   const DamageParams& params);

/// The documented decision: decideDamage(...).verdict == Damaged (all regions trusted:
/// damageScore(...) >= params.flagScore). With the default 0.5: damaged
/// when the regions together cover at least damagedShare of the tissue, or one tear is a crack
/// at least deepTearFrac of the brain width long and at least crackElongation times longer than
/// its thickest width.
bool isDamaged(const std::vector<DamageRegion>& regions, double brainWidthPx,
               const DamageParams& params);

/// Misfit (issue 18, item 1): sets DamageRegion::excessShare, excessVentricleShare and misfit
/// of every gap (Tear and Missing) of `regions`. `tissueMask`: the section's tissue (CV_8U);
/// `expected`: the mapped atlas (tissue and brain) at that size; `fragments` (CV_8U or empty)
/// and the Fragment regions: detached pieces, which lie outside the atlas brain by being damage
/// and do not count as misplaced tissue. Region polygons and lengths are in pixels of a frame
/// `polygonScale` times coarser than the masks' (polygon px x polygonScale = mask px).
void markMisfit(std::vector<DamageRegion>& regions, const cv::Mat& tissueMask,
                const AtlasExpectation& expected, double brainWidthPx, const DamageParams& params,
                const cv::Mat& fragments = cv::Mat(), double polygonScale = 1.0);

/// Bilateral anatomy (issue 18): the brain is mirror-symmetric across its midline, and so are its
/// ventricles, its clefts and what a plane cut off both sides; damage is not. Of the pixels of
/// `region` (CV_8U), each mapped into atlas px by `atlasX`, `atlasY` (CV_32F, the registration's
/// map, the region's size) and mirrored across the atlas column `midlineX`, the share landing on
/// `partner` (CV_8U, atlas frame: what a twin would show there, such as the section's glass
/// grown by the slack), counting only those landing where the section was seen (`known`, CV_8U,
/// atlas frame) and not on the region itself grown by `selfPx` atlas px (a gap across the
/// midline is its own mirror image and proves nothing). -1 when fewer than half the region's
/// pixels have such a mirror image (undecided).
double mirroredShare(const cv::Mat& region, const cv::Mat& atlasX, const cv::Mat& atlasY,
                     double midlineX, const cv::Mat& partner, const cv::Mat& known, int selfPx);

/// The section's verdict and score.
struct DamageDecision {
    DamageVerdict verdict = DamageVerdict::Clean;
    /// Damaged and Clean: damageScore over the regions the fit is trusted around (misfit false);
    /// CheckRegistration: damageScore over all regions (how much tissue looks missing).
    double score = 0;
};

/// The verdict (issue 18, item 1): Damaged when the regions the atlas fit can be trusted around
/// reach params.flagScore on their own (true damage decides, whatever misfit lies beside it);
/// otherwise CheckRegistration when all regions together reach it (the tissue looks missing
/// only with the gaps where the atlas is not trusted); otherwise Clean. Sets every region's
/// score (damageEvidence of the region alone).
DamageDecision decideDamage(std::vector<DamageRegion>& regions, double brainWidthPx,
                            const DamageParams& params);

/// A short human-readable summary ("tear 3.1%, missing 1.2% of the tissue" / "no damage").
std::string damageSummary(const std::vector<DamageRegion>& regions);

} // namespace slicestation::pipeline
