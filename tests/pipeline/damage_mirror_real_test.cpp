// Bilateral anatomy on real sections (issue 18; docs/damage.md, "Bilateral anatomy"): gaps of
// abba-gerbi-series whose mirror image across the brain's midline shows glass too are anatomy
// (both lateral ventricles wider than the atlas's; tissue the atlas plane has and the section
// lacks on both sides), so are pieces lying apart whose mirror image is tissue, and a one-sided
// tear keeps its flag; and a torn section's crack, followed where it narrows, flags it. Also
// the registration's placement on a real section under a known warp (issue 17, item 3).
#include "../common/gerbi_series.hpp"
#include "../common/known_warp.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/damage_series.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <random>

using namespace slicestation;
namespace fs = std::filesystem;

namespace {

const fs::path kAtlas = fs::path(SLST_SHARED_DIR) / "atlas" / "allen-ccf-2017";
const fs::path kGerbi = fs::path(SLST_SHARED_DIR) / "sections" / "abba-gerbi-series";

bool haveGerbi() {
    return fs::exists(kGerbi / "sections.csv") &&
           fs::exists(kAtlas / "annotation_25_quicknii.nrrd");
}

/// One gerbi section and its atlas plane, cut at its curated position and tilt (sections.csv,
/// README) as slst_bench_consistency does.
struct GerbiSection {
    cv::Mat image, atlas;
    double umPerPx = 0;
};
GerbiSection gerbiSection(int number) {
    static const auto volume = core::readNrrd(kAtlas / "annotation_25_quicknii.nrrd");
    static const auto onto = core::readOntologyCsv(kAtlas / "structure_tree_safe_2017.csv");
    EXPECT_TRUE(volume.ok() && onto.ok());
    if (!volume || !onto)
        return {};
    const auto rows = testing_abba::readGerbiRows(kGerbi);
    EXPECT_TRUE(rows.ok()) << rows.error().message;
    for (const testing_abba::GerbiRow& row : rows ? *rows : std::vector<testing_abba::GerbiRow>{}) {
        if (row.number != number)
            continue;
        GerbiSection out;
        auto image = core::readImage(kGerbi / row.file);
        EXPECT_TRUE(image.ok());
        if (!image)
            return {};
        out.image = *image;
        out.umPerPx = row.umPerPx;
        auto labels = testing_abba::gerbiPlaneLabels(*volume, row.abbaMm);
        EXPECT_TRUE(labels.ok());
        if (!labels)
            return {};
        out.atlas = pipeline::collapseLabels(*labels, *onto, pipeline::majorRegionIds(), 8);
        return out;
    }
    ADD_FAILURE() << "gerbi section " << number << " is not in sections.csv";
    return {};
}

pipeline::Registration registerGerbi(const GerbiSection& s, bool leaveOutMirrored,
                                     pipeline::DamageParams damage = {}) {
    pipeline::RegistrationOptions ro;
    ro.imageUmPerPx = s.umPerPx;
    ro.atlasUmPerPx = 25;
    ro.damage = damage;
    ro.damage.leaveOutMirroredGaps = leaveOutMirrored;
    auto reg = pipeline::registerSection(s.image, s.atlas, ro);
    EXPECT_TRUE(reg.ok()) << reg.error().message;
    return reg ? std::move(*reg) : pipeline::Registration{};
}

} // namespace

TEST(DamageRealSeries, GapsWithAMirroredTwinAreAnatomyAndAOneSidedTearIsNot) {
    if (!haveGerbi())
        GTEST_SKIP() << "../shared is absent: real sections not tested";
    // 15: both lateral ventricles wider than the atlas's; 22: ventral tissue the plane has and
    // the section lacks on both sides; 25: the cortex apart from the brain stem on both sides,
    // the left piece taken for a fragment. Clean by eye, flagged without the rule.
    for (int n : {15, 22, 25}) {
        const GerbiSection s = gerbiSection(n);
        ASSERT_FALSE(s.image.empty());
        const pipeline::Registration without = registerGerbi(s, false);
        EXPECT_TRUE(without.damaged) << n << " without the rule: " << without.damageSummary;
        bool twin = false;
        for (const pipeline::DamageRegion& d : without.damage)
            twin |= d.mirrorShare >= pipeline::DamageParams{}.mirroredGap;
        EXPECT_TRUE(twin) << n << ": no region with a mirrored twin";
        const pipeline::Registration with = registerGerbi(s, true);
        EXPECT_FALSE(with.damaged) << n << ": " << with.damageSummary;
    }
    // 02: the right frontal cortex piece is missing; the left is there, so the gaps have no twin.
    const GerbiSection torn = gerbiSection(2);
    ASSERT_FALSE(torn.image.empty());
    const pipeline::Registration reg = registerGerbi(torn, true);
    EXPECT_TRUE(reg.damaged) << reg.damageSummary;
    for (const pipeline::DamageRegion& d : reg.damage) {
        if (d.kind == pipeline::DamageKind::Tear || d.kind == pipeline::DamageKind::Missing) {
            EXPECT_LT(d.mirrorShare, pipeline::DamageParams{}.mirroredGap);
        }
    }
}

TEST(DamageRealSeries, ATornSectionsCrackIsFollowedWhereItNarrowsAtItsBend) {
    if (!haveGerbi())
        GTEST_SKIP() << "../shared is absent: real sections not tested";
    // 14: a crack from the left lateral surface into the cortex, bending at a bright speck. Its
    // inner, oblique half is a tear (under a tenth of the width: not flagged alone); its outer
    // half is a 1-2 px line, a piece too short alone; where it bends, the crack is a shallow
    // line only. Followed across, the tear is long enough to flag the section. The gaps above
    // both lateral ventricles (bilateral, mirror share 1) are left out by the rule.
    const GerbiSection s = gerbiSection(14);
    ASSERT_FALSE(s.image.empty());
    const pipeline::Registration with = registerGerbi(s, true);
    EXPECT_TRUE(with.damaged) << with.damageSummary;
    pipeline::DamageParams noPieces;
    noPieces.crackPieceFrac = 0;
    const pipeline::Registration without = registerGerbi(s, true, noPieces);
    EXPECT_FALSE(without.damaged) << without.damageSummary;
    EXPECT_GT(with.damageScore, without.damageScore + 0.05);
}

TEST(DamageRealSeries, AWideVentricleTheEarlierSectionsShowIsNoTear) {
    if (!haveGerbi())
        GTEST_SKIP() << "../shared is absent: real sections not tested";
    // 07 (clean): its right lateral ventricle's lumen is wider than the atlas's, a band along the
    // lumen flagged alone; 06 shows that ventricle wider than its own atlas's too (glass where
    // its atlas expects tissue), 05 does not. Judged live with 06 and 05, the band has half its
    // context (persistence 0.5) and the section is not flagged; with their gaps only (06 and 05
    // make none there) it is. The planes of one series share one pixel grid.
    std::map<int, pipeline::Registration> reg;
    for (int n : {5, 6, 7}) {
        const GerbiSection s = gerbiSection(n);
        ASSERT_FALSE(s.image.empty());
        reg[n] = registerGerbi(s, true);
    }
    pipeline::Registration alone = reg[7];
    ASSERT_TRUE(alone.damaged) << alone.damageSummary;
    bool band = false;
    for (const pipeline::DamageRegion& d : alone.damage)
        band |= d.alongVentricle;
    EXPECT_TRUE(band) << alone.damageSummary;
    const pipeline::SectionShown six = pipeline::shownInSeries(reg[6]);
    const pipeline::SectionShown five = pipeline::shownInSeries(reg[5]);
    EXPECT_FALSE(six.glass.empty());
    const pipeline::DamageParams dp;
    pipeline::Registration gapsOnly = reg[7];
    pipeline::judgeInSeries(gapsOnly, {{six.gaps, {}}, {five.gaps, {}}}, dp, {});
    EXPECT_TRUE(gapsOnly.damaged) << gapsOnly.damageScore;
    pipeline::Registration live = reg[7];
    pipeline::judgeInSeries(live, {six, five}, dp, {});
    EXPECT_FALSE(live.damaged) << live.damageScore;
    EXPECT_LT(live.damageScore, alone.damageScore);
}

namespace {

/// Gerbi `section` registered as it is and under the first `warps` known warps of seed 17
/// (tests/common/known_warp.hpp, the consistency benchmark's): every warp's mapping within 25
/// atlas px of the original's (a placement turned over maps 100-400 px off).
void expectTheSameWayUpUnderKnownWarps(int section, int warps) {
    const GerbiSection s = gerbiSection(section);
    ASSERT_FALSE(s.image.empty());
    pipeline::RegistrationOptions ro;
    ro.imageUmPerPx = s.umPerPx;
    ro.atlasUmPerPx = 25;
    auto reg0 = pipeline::registerSection(s.image, s.atlas, ro);
    ASSERT_TRUE(reg0.ok()) << reg0.error().message;
    cv::Mat tissue;
    cv::resize(reg0->workingTissueMask, tissue, s.image.size(), 0, 0, cv::INTER_NEAREST);
    std::mt19937_64 rng(17);
    for (int k = 0; k < warps; ++k) {
        const testing_warp::Warp w = testing_warp::randomWarp(rng, s.image.size(), false, 1.0);
        auto reg1 = pipeline::registerSection(testing_warp::applyWarp(s.image, w), s.atlas, ro);
        ASSERT_TRUE(reg1.ok()) << reg1.error().message;
        const testing_warp::WarpDifference diff = testing_warp::differenceOverTissue(
            w, tissue, [&](cv::Point2d q) { return reg1->atlasFromImage(q); },
            [&](cv::Point2d p) { return reg0->atlasFromImage(p); });
        ASSERT_GT(diff.points, 1000);
        EXPECT_LT(diff.rms(), 25.0) << "section " << section << ", warp " << k;
    }
}

} // namespace

// The known warps of slst_bench_consistency (seed 17, gerbi section 09 run alone): under the
// third, the placement and its upside-down twin come out of the full ICP in a near tie of edge
// agreement (0.424 and 0.425), and the region fit preferred the twin (0.618 against 0.545), so
// the warped section mapped 150-220 atlas px from where the original maps. Their polished
// outline overlaps (0.951 and 0.923) settle it the right way up (docs/registration.md, "Near
// ties settled by the outline first"; since then through the product of the two misfits, "Which
// way up"). Every warp's mapping must agree with the original's
// composed with the known warp, as the benchmark measures it, within its gross bound (25 px).
TEST(RegistrationRealSeries, ANearTieWithTheUpsideDownTwinIsSettledByTheOutline) {
    if (!haveGerbi())
        GTEST_SKIP() << "needs ../shared (abba-gerbi-series and the 25 um annotation)";
    expectTheSameWayUpUnderKnownWarps(9, 3);
}

// Which way up (docs/registration.md, "Which way up: the least misfit of outline and edges"):
// gerbi section 10 under the first seven known warps of seed 17. Under the seventh the earlier
// rule (edge agreement beyond 0.02, then the outline overlap beyond 0.02, then the region fit)
// kept the placement upside down (232.9 atlas px off); the product of the edges' and the
// outline's misfits keeps the right one.
TEST(RegistrationRealSeries, TheWayUpIsTheLeastMisfitOfOutlineAndEdges) {
    if (!haveGerbi())
        GTEST_SKIP() << "needs ../shared (abba-gerbi-series and the 25 um annotation)";
    expectTheSameWayUpUnderKnownWarps(10, 7);
}
