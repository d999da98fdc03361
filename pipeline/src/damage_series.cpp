#include "slicestation/pipeline/damage_series.hpp"

#include "slicestation/pipeline/mask_ops.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>

namespace slicestation::pipeline {

namespace {

std::vector<cv::Point> shifted(const std::vector<cv::Point2f>& polygon, cv::Point2f origin) {
    std::vector<cv::Point> out;
    out.reserve(polygon.size());
    for (const cv::Point2f& p : polygon)
        out.emplace_back(cvRound(p.x - origin.x), cvRound(p.y - origin.y));
    return out;
}

/// An outline in full-resolution px, subdivided to `maxSegmentPx` so that a curved map bends it,
/// mapped through `reg` (affine and warp) into atlas px.
std::vector<cv::Point2f> outlineInAtlas(const Registration& reg,
                                        const std::vector<cv::Point2f>& outline,
                                        double maxSegmentPx) {
    std::vector<cv::Point2f> out;
    for (const cv::Point2f& p : subdivide(outline, maxSegmentPx)) {
        const cv::Point2d a = reg.atlasFromImage(cv::Point2d(p.x, p.y));
        out.emplace_back(float(a.x), float(a.y));
    }
    return out;
}

} // namespace

double persistenceAmong(const std::vector<cv::Point2f>& region,
                        const std::vector<AtlasDamageOutlines>& neighbours,
                        const SeriesContextParams& params) {
    if (region.size() < 3 || neighbours.empty())
        return 0;
    // Rasterise in the region's box grown by the slack: only neighbours' outlines there matter.
    const int slack = std::max(0, static_cast<int>(std::lround(params.slackAtlasPx)));
    const cv::Rect box = cv::boundingRect(region);
    const cv::Point2f origin(float(box.x - slack - 1), float(box.y - slack - 1));
    const cv::Size size(box.width + 2 * slack + 3, box.height + 2 * slack + 3);
    cv::Mat mine = cv::Mat::zeros(size, CV_8U);
    cv::fillPoly(mine, std::vector<std::vector<cv::Point>>{shifted(region, origin)},
                 cv::Scalar(255));
    const double area = cv::countNonZero(mine);
    if (area <= 0)
        return 0;
    const cv::Mat grow =
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * slack + 1, 2 * slack + 1));
    int same = 0;
    for (const AtlasDamageOutlines& section : neighbours) {
        cv::Mat theirs = cv::Mat::zeros(size, CV_8U);
        for (const auto& polygon : section)
            if (polygon.size() >= 3)
                cv::fillPoly(theirs, std::vector<std::vector<cv::Point>>{shifted(polygon, origin)},
                             cv::Scalar(255));
        if (slack > 0)
            cv::dilate(theirs, theirs, grow);
        if (cv::countNonZero(theirs & mine) >= params.samePlaceShare * area)
            ++same;
        else if (params.contiguous)
            break;
    }
    return double(same) / double(std::max<std::size_t>(neighbours.size(),
                                                       std::size_t(std::max(1, params.window))));
}

double applySeriesContext(std::vector<DamageRegion>& regions,
                          const AtlasDamageOutlines& regionsAtlas,
                          const std::vector<AtlasDamageOutlines>& neighbours, double brainWidthPx,
                          const DamageParams& damageParams, const SeriesContextParams& params) {
    for (size_t i = 0; i < regions.size(); ++i)
        regions[i].persistence =
            i < regionsAtlas.size() ? persistenceAmong(regionsAtlas[i], neighbours, params) : 0.0;
    return damageScore(regions, brainWidthPx, damageParams);
}

std::vector<cv::Point2f> atlasDamageOutline(const Registration& reg, const DamageRegion& d,
                                            double maxSegmentPx) {
    if ((d.kind != DamageKind::Tear && d.kind != DamageKind::Missing) || d.polygon.size() < 3)
        return {};
    return outlineInAtlas(reg, d.polygon, maxSegmentPx);
}

AtlasDamageOutlines atlasDamageOutlines(const Registration& reg, double maxSegmentPx) {
    AtlasDamageOutlines out(reg.damage.size());
    for (std::size_t i = 0; i < reg.damage.size(); ++i) {
        const DamageRegion& d = reg.damage[i];
        out[i] = d.atlasOutline.empty() ? atlasDamageOutline(reg, d, maxSegmentPx) : d.atlasOutline;
    }
    return out;
}

cv::Mat glassWhereTissueIsExpected(const cv::Mat& tissue, const cv::Mat& expectedTissue,
                                   int slackPx) {
    CV_Assert(tissue.type() == CV_8U && expectedTissue.type() == CV_8U &&
              tissue.size() == expectedTissue.size() && slackPx >= 0);
    cv::Mat inner;
    cv::erode(
        expectedTissue, inner,
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * slackPx + 1, 2 * slackPx + 1)));
    return fillHoles(tissue) & ~tissue & inner;
}

std::vector<std::vector<cv::Point2f>> glassOutlines(const Registration& reg, const cv::Mat& glass,
                                                    double minAreaPx, double maxSegmentPx) {
    CV_Assert(glass.type() == CV_8U);
    std::vector<std::vector<cv::Point2f>> out;
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(glass, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    const double s = reg.workingScale; // working px = (full px + 0.5) s - 0.5
    for (const std::vector<cv::Point>& c : contours) {
        if (c.size() < 3 || cv::contourArea(c) < minAreaPx)
            continue;
        std::vector<cv::Point2f> full;
        full.reserve(c.size());
        for (const cv::Point& p : c)
            full.emplace_back(float((p.x + 0.5) / s - 0.5), float((p.y + 0.5) / s - 0.5));
        out.push_back(outlineInAtlas(reg, full, maxSegmentPx));
    }
    return out;
}

SectionShown shownInSeries(const Registration& reg, double maxSegmentPx) {
    return {atlasDamageOutlines(reg, maxSegmentPx), reg.glassAtlas};
}

DamageDecision judgeInSeries(Registration& reg, const std::vector<SectionShown>& earlier,
                             const DamageParams& damageParams, const SeriesContextParams& params) {
    const std::size_t n = std::min(earlier.size(), std::size_t(std::max(0, params.window)));
    std::vector<AtlasDamageOutlines> gaps, gapsAndGlass;
    for (std::size_t k = 0; k < n; ++k) {
        gaps.push_back(earlier[k].gaps);
        gapsAndGlass.push_back(earlier[k].gaps);
        gapsAndGlass.back().insert(gapsAndGlass.back().end(), earlier[k].glass.begin(),
                                   earlier[k].glass.end());
    }
    const AtlasDamageOutlines mine = atlasDamageOutlines(reg);
    for (std::size_t i = 0; i < reg.damage.size(); ++i)
        reg.damage[i].persistence =
            persistenceAmong(mine[i], reg.damage[i].alongVentricle ? gapsAndGlass : gaps, params);
    const double brainWidthPx = reg.brainWidthPx;
    const DamageDecision decision = decideDamage(reg.damage, brainWidthPx, damageParams);
    reg.damageScore = decision.score;
    reg.damageVerdict = decision.verdict;
    reg.damaged = decision.verdict == DamageVerdict::Damaged;
    return decision;
}

} // namespace slicestation::pipeline
