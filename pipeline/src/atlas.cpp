#include "slicestation/pipeline/atlas.hpp"

#include <algorithm>
#include <limits>
#include <map>
#include <unordered_map>

namespace slicestation::pipeline {

using core::ErrorCode;
using core::makeError;

core::Result<cv::Mat> labelsFromImage(const cv::Mat& image) {
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "atlas label image is empty");
    cv::Mat labels;
    const int depth = image.depth();
    if (image.channels() == 1) {
        if (depth == CV_32F || depth == CV_64F)
            return makeError(
                ErrorCode::InvalidArgument,
                "atlas label image has floating-point pixels; labels must be integers");
        if (depth == CV_8S || depth == CV_16S)
            return makeError(ErrorCode::InvalidArgument, "atlas label image has signed pixels");
        image.convertTo(labels, CV_32S);
    } else if ((image.channels() == 3 || image.channels() == 4) && depth == CV_8U) {
        // Colour-coded atlas: pack each colour into one id, then call the border's colour 0.
        labels.create(image.size(), CV_32S);
        const int ch = image.channels();
        for (int y = 0; y < image.rows; ++y) {
            const uchar* p = image.ptr<uchar>(y);
            int* o = labels.ptr<int>(y);
            for (int x = 0; x < image.cols; ++x, p += ch)
                o[x] = (p[2] << 16) | (p[1] << 8) | p[0];
        }
        std::map<int, int> border;
        for (int x = 0; x < labels.cols; ++x) {
            ++border[labels.at<int>(0, x)];
            ++border[labels.at<int>(labels.rows - 1, x)];
        }
        for (int y = 0; y < labels.rows; ++y) {
            ++border[labels.at<int>(y, 0)];
            ++border[labels.at<int>(y, labels.cols - 1)];
        }
        const int outside = std::max_element(border.begin(), border.end(), [](auto& a, auto& b) {
                                return a.second < b.second;
                            })->first;
        // Keep ids distinct from 0: black regions (0x000000) inside become a separate id.
        labels.setTo(0x1000000, labels == 0);
        labels.setTo(0, labels == (outside == 0 ? 0x1000000 : outside));
    } else {
        return makeError(ErrorCode::InvalidArgument,
                         "atlas label image must be single-channel ids or 8-bit colour-coded RGB");
    }
    if (cv::countNonZero(labels) == 0)
        return makeError(ErrorCode::InvalidArgument, "atlas label image has no labels (all 0)");
    return labels;
}

core::Result<cv::Mat> coronalPlane(const core::Volume& volume, VolumeAxes axes, int apIndex) {
    const auto& s = volume.sizes;
    const int apSize = axes == VolumeAxes::Allen ? s[0] : s[1];
    if (apIndex < 0 || apIndex >= apSize)
        return makeError(ErrorCode::OutOfRange, "coronal index " + std::to_string(apIndex) +
                                                    " is outside the volume (0.." +
                                                    std::to_string(apSize - 1) + ")");
    const int rows = axes == VolumeAxes::Allen ? s[1] : s[2];
    const int cols = axes == VolumeAxes::Allen ? s[2] : s[0];
    cv::Mat plane(rows, cols, CV_32S);
    for (int r = 0; r < rows; ++r) {
        int* o = plane.ptr<int>(r);
        for (int c = 0; c < cols; ++c) {
            const std::uint32_t v = axes == VolumeAxes::Allen
                                        ? volume.at(apIndex, r, c)
                                        : volume.at(c, s[1] - 1 - apIndex, s[2] - 1 - r);
            if (v > std::uint32_t(std::numeric_limits<int>::max()))
                return makeError(ErrorCode::InvalidArgument,
                                 "label id " + std::to_string(v) + " does not fit 31 bits");
            o[c] = static_cast<int>(v);
        }
    }
    return plane;
}

const std::vector<std::uint32_t>& majorRegionIds() {
    static const std::vector<std::uint32_t> ids{315, 698, 1080, 822, 703,  278, 56,   754,
                                                672, 275, 998,  803, 549,  958, 1097, 313,
                                                771, 354, 519,  528, 1009, 73};
    return ids;
}

void collectIds(const cv::Mat& labels, std::set<std::int32_t>& ids) {
    CV_Assert(labels.type() == CV_32S);
    for (auto it = labels.begin<std::int32_t>(); it != labels.end<std::int32_t>(); ++it)
        if (*it != 0)
            ids.insert(*it);
}

std::vector<std::int32_t> idsUnder(const std::set<std::int32_t>& ids,
                                   const core::Ontology& ontology, std::uint32_t ancestorId) {
    std::vector<std::int32_t> out;
    for (std::int32_t id : ids)
        if (ontology.isDescendantOf(std::uint32_t(id), ancestorId))
            out.push_back(id);
    return out;
}

cv::Mat collapseLabels(const cv::Mat& labels, const core::Ontology& ontology,
                       const std::vector<std::uint32_t>& regionIds, std::int32_t otherId) {
    CV_Assert(labels.type() == CV_32S);
    std::unordered_map<int, int> cache;
    cv::Mat out(labels.size(), CV_32S);
    for (int y = 0; y < labels.rows; ++y) {
        const int* in = labels.ptr<int>(y);
        int* o = out.ptr<int>(y);
        for (int x = 0; x < labels.cols; ++x) {
            const int id = in[x];
            if (id == 0) {
                o[x] = 0;
                continue;
            }
            auto it = cache.find(id);
            if (it == cache.end()) {
                int mapped = otherId;
                if (const core::Structure* s = ontology.find(static_cast<std::uint32_t>(id))) {
                    // Deepest listed ancestor: walk the path from the leaf upwards.
                    for (auto p = s->path.rbegin(); p != s->path.rend(); ++p) {
                        if (std::find(regionIds.begin(), regionIds.end(), *p) != regionIds.end()) {
                            mapped = static_cast<int>(*p);
                            break;
                        }
                    }
                }
                it = cache.emplace(id, mapped).first;
            }
            o[x] = it->second;
        }
    }
    return out;
}

} // namespace slicestation::pipeline
