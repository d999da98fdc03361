#include "slicestation/pipeline/frame_image.hpp"

#include <opencv2/imgproc.hpp>

#include <cstring>

namespace slicestation::pipeline {

cv::Mat frameToMat(const hw::Frame& frame) {
    if (frame.empty() || frame.width() <= 0 || frame.height() <= 0)
        return {};
    const int type = frame.format() == hw::PixelFormat::Mono16 ? CV_16UC1
                     : frame.format() == hw::PixelFormat::Rgb8 ? CV_8UC3
                                                               : CV_8UC1;
    cv::Mat out(frame.height(), frame.width(), type);
    for (int y = 0; y < frame.height(); ++y) {
        std::memcpy(out.ptr(y), frame.row(y), frame.stride());
    }
    if (type == CV_8UC3)
        cv::cvtColor(out, out, cv::COLOR_RGB2BGR);
    return out;
}

} // namespace slicestation::pipeline
