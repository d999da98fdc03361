#include "slicestation/pipeline/overlay.hpp"

#include "slicestation/pipeline/edges.hpp"

#include <opencv2/imgproc.hpp>

namespace slicestation::pipeline {

cv::Mat renderOverlay(const cv::Mat& sectionGrey, const cv::Mat& labelsInImage,
                      const std::vector<std::vector<cv::Point2f>>& damagePolygons) {
    CV_Assert(sectionGrey.type() == CV_32F && labelsInImage.type() == CV_32S &&
              sectionGrey.size() == labelsInImage.size());
    cv::Mat u8, bgr;
    sectionGrey.convertTo(u8, CV_8U, 255.0);
    cv::cvtColor(u8, bgr, cv::COLOR_GRAY2BGR);
    if (!damagePolygons.empty()) {
        cv::Mat layer = bgr.clone();
        std::vector<std::vector<cv::Point>> polys;
        for (const auto& poly : damagePolygons) {
            std::vector<cv::Point> p;
            for (const auto& q : poly)
                p.emplace_back(cvRound(q.x), cvRound(q.y));
            polys.push_back(std::move(p));
        }
        cv::fillPoly(layer, polys, cv::Scalar(0, 0, 255));
        cv::addWeighted(layer, 0.45, bgr, 0.55, 0, bgr);
        cv::polylines(bgr, polys, true, cv::Scalar(0, 0, 255), 2);
    }
    // Internal boundaries in yellow, the brain outline in cyan, thickened on large images.
    const cv::Mat edges = atlasEdges(labelsInImage);
    cv::Mat brain;
    cv::Mat(labelsInImage != 0).convertTo(brain, CV_32S);
    cv::Mat e = edges, o = atlasEdges(brain);
    const int t = std::max(1, std::max(bgr.cols, bgr.rows) / 900);
    if (t > 1) {
        const cv::Mat k = cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(t, t));
        cv::dilate(e, e, k);
        cv::dilate(o, o, k);
    }
    bgr.setTo(cv::Scalar(0, 220, 255), e);
    bgr.setTo(cv::Scalar(255, 255, 0), o);
    return bgr;
}

cv::Mat renderOverlay(const Registration& reg, const cv::Mat& atlasLabels) {
    // Damage polygons come in full-resolution pixels; the overlay is at working size.
    std::vector<std::vector<cv::Point2f>> damage;
    for (const DamageRegion& d : reg.damage) {
        std::vector<cv::Point2f> poly;
        for (const cv::Point2f& p : d.polygon)
            poly.emplace_back(reg.workingFromImage(p));
        damage.push_back(std::move(poly));
    }
    return renderOverlay(reg.workingGrey, reg.warpedLabels(atlasLabels, reg.workingGrey.size()),
                         damage);
}

} // namespace slicestation::pipeline
