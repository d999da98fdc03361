#include "slicestation/daemon/export/section_export.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/region_outlines.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <fstream>
#include <map>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

namespace {

cv::Matx23d compose(const cv::Matx23d& a, const cv::Matx23d& b) {
    // a after b
    cv::Matx33d A(a(0, 0), a(0, 1), a(0, 2), a(1, 0), a(1, 1), a(1, 2), 0, 0, 1);
    cv::Matx33d B(b(0, 0), b(0, 1), b(0, 2), b(1, 0), b(1, 1), b(1, 2), 0, 0, 1);
    const cv::Matx33d c = A * B;
    return {c(0, 0), c(0, 1), c(0, 2), c(1, 0), c(1, 1), c(1, 2)};
}

cv::Point2d apply(const cv::Matx23d& a, cv::Point2d p) {
    return {a(0, 0) * p.x + a(0, 1) * p.y + a(0, 2), a(1, 0) * p.x + a(1, 1) * p.y + a(1, 2)};
}

json vec3(const cv::Vec3d& v) {
    return json::array({v[0], v[1], v[2]});
}

core::Result<cv::Vec3d> vec3From(const json& j, const char* key) {
    if (!j.contains(key) || !j[key].is_array() || j[key].size() != 3)
        return makeError(ErrorCode::InvalidArgument,
                         std::string("\"") + key + "\": expected 3 numbers");
    cv::Vec3d v;
    for (int i = 0; i < 3; ++i) {
        if (!j[key][std::size_t(i)].is_number())
            return makeError(ErrorCode::InvalidArgument,
                             std::string("\"") + key + "\": expected 3 numbers");
        v[i] = j[key][std::size_t(i)].get<double>();
    }
    return v;
}

core::Result<double> number(const json& j, const char* key) {
    if (!j.is_object() || !j.contains(key) || !j[key].is_number())
        return makeError(ErrorCode::InvalidArgument,
                         std::string("\"") + key + "\": expected a number");
    return j[key].get<double>();
}

} // namespace

// --- the saved mapping ---------------------------------------------------------------------

cv::Matx23d SavedMapping::affineAtlasFromImage() const {
    const double s = workingScale, o = 0.5 * s - 0.5;
    return compose(atlasFromWorking, cv::Matx23d(s, 0, o, 0, s, o));
}

cv::Point2d SavedMapping::atlasFromImage(cv::Point2d p) const {
    const cv::Point2d w{(p.x + 0.5) * workingScale - 0.5, (p.y + 0.5) * workingScale - 0.5};
    cv::Point2d a = apply(atlasFromWorking, w);
    if (dx.empty())
        return a;
    // As pipeline::DisplacementField::at: bilinear between nodes, clamped to the grid.
    const double gx = std::clamp(w.x / cellPx, 0.0, double(dx.cols - 1));
    const double gy = std::clamp(w.y / cellPx, 0.0, double(dx.rows - 1));
    const int x0 = std::min(static_cast<int>(gx), std::max(dx.cols - 2, 0));
    const int y0 = std::min(static_cast<int>(gy), std::max(dx.rows - 2, 0));
    const int x1 = std::min(x0 + 1, dx.cols - 1), y1 = std::min(y0 + 1, dx.rows - 1);
    const double fx = gx - x0, fy = gy - y0;
    auto bil = [&](const cv::Mat& m) {
        return (1 - fy) * ((1 - fx) * m.at<float>(y0, x0) + fx * m.at<float>(y0, x1)) +
               fy * ((1 - fx) * m.at<float>(y1, x0) + fx * m.at<float>(y1, x1));
    };
    return a + cv::Point2d(bil(dx), bil(dy));
}

void SavedMapping::atlasMaps(cv::Size size, cv::Mat& mapX, cv::Mat& mapY) const {
    mapX.create(size, CV_32F);
    mapY.create(size, CV_32F);
    const double sx = double(imageSize.width) / size.width;
    const double sy = double(imageSize.height) / size.height;
    for (int y = 0; y < size.height; ++y) {
        auto* mx = mapX.ptr<float>(y);
        auto* my = mapY.ptr<float>(y);
        for (int x = 0; x < size.width; ++x) {
            const cv::Point2d a = atlasFromImage({(x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5});
            mx[x] = float(a.x);
            my[x] = float(a.y);
        }
    }
}

SavedMapping savedMapping(const pipeline::Registration& r) {
    SavedMapping m;
    m.imageSize = r.imageSize;
    m.workingScale = r.workingScale;
    m.atlasFromWorking = r.atlasFromWorking;
    if (!r.warp.empty()) {
        m.cellPx = r.warp.cellPx();
        m.dx = r.warp.dx().clone();
        m.dy = r.warp.dy().clone();
    }
    return m;
}

core::Result<void> writeMappingField(const std::filesystem::path& path, const SavedMapping& m) {
    cv::Mat planes;
    if (m.dx.empty())
        planes = cv::Mat::zeros(1, 1, CV_32FC2);
    else
        cv::merge(std::vector<cv::Mat>{m.dx, m.dy}, planes);
    return core::writeImage(path, planes);
}

json mappingJson(const SavedMapping& m, const std::string& fieldFile) {
    const cv::Matx23d& a = m.atlasFromWorking;
    const int cols = m.dx.empty() ? 1 : m.dx.cols, rows = m.dx.empty() ? 1 : m.dx.rows;
    return {
        {"field", fieldFile},
        {"field_units", "atlas px"},
        {"field_cols", cols},
        {"field_rows", rows},
        {"field_node_spacing_working_px", m.cellPx},
        {"working_scale", m.workingScale},
        {"affine_atlas_from_working", {{a(0, 0), a(0, 1), a(0, 2)}, {a(1, 0), a(1, 1), a(1, 2)}}},
        {"grid", "image px p -> working w = (p + 0.5) * working_scale - 0.5; atlas = "
                 "affine_atlas_from_working * w + field(w); field node (i, j) at w = (j, i) * "
                 "field_node_spacing_working_px, bilinear, clamped to the outermost nodes"}};
}

core::Result<SavedMapping> readSavedMapping(const json& result,
                                            const std::filesystem::path& resultDir) {
    if (!result.is_object() || !result.contains("mapping") || !result["mapping"].is_object())
        return makeError(
            ErrorCode::InvalidArgument,
            "result has no \"mapping\" (written before the full mapping was kept: register again)");
    const json& j = result["mapping"];
    SavedMapping m;
    auto scale = number(j, "working_scale");
    auto cell = number(j, "field_node_spacing_working_px");
    auto w = number(result.value("image", json::object()), "width");
    auto h = number(result.value("image", json::object()), "height");
    for (const auto* r : {&scale, &cell, &w, &h})
        if (!*r)
            return makeError(ErrorCode::InvalidArgument, "result mapping: " + r->error().message);
    if (!(*scale > 0 && *cell > 0 && *w >= 1 && *h >= 1 && *w <= 1e6 && *h <= 1e6))
        return makeError(ErrorCode::InvalidArgument,
                         "result mapping: scale, node spacing or image size out of range");
    m.workingScale = *scale;
    m.cellPx = *cell;
    m.imageSize = {int(*w), int(*h)};
    const json& a = j.value("affine_atlas_from_working", json());
    if (!a.is_array() || a.size() != 2 || !a[0].is_array() || a[0].size() != 3 ||
        !a[1].is_array() || a[1].size() != 3)
        return makeError(ErrorCode::InvalidArgument,
                         "result mapping: \"affine_atlas_from_working\" must be 2 x 3 numbers");
    for (int r = 0; r < 2; ++r)
        for (int c = 0; c < 3; ++c) {
            const json& v = a[std::size_t(r)][std::size_t(c)];
            if (!v.is_number())
                return makeError(ErrorCode::InvalidArgument,
                                 "result mapping: \"affine_atlas_from_working\" must be numbers");
            m.atlasFromWorking(r, c) = v.get<double>();
        }
    if (!j.contains("field") || !j["field"].is_string())
        return makeError(ErrorCode::InvalidArgument,
                         "result mapping: \"field\" must be a file name");
    auto field = core::readImage(resultDir / j["field"].get<std::string>());
    if (!field)
        return field.error();
    if (field->type() != CV_32FC2)
        return makeError(ErrorCode::InvalidArgument,
                         "field " + j["field"].get<std::string>() +
                             ": expected two float32 samples per pixel (dx, dy)");
    const int cols = j.value("field_cols", field->cols), rows = j.value("field_rows", field->rows);
    if (field->cols != cols || field->rows != rows)
        return makeError(ErrorCode::InvalidArgument,
                         "field " + j["field"].get<std::string>() + " has " +
                             std::to_string(field->cols) + " x " + std::to_string(field->rows) +
                             " nodes, the result says " + std::to_string(cols) + " x " +
                             std::to_string(rows));
    std::vector<cv::Mat> planes;
    cv::split(*field, planes);
    if (field->total() > 1) {
        m.dx = planes[0];
        m.dy = planes[1];
    }
    return m;
}

// --- the atlas slice's frame ---------------------------------------------------------------

AtlasSliceFrame sliceFrame(const AtlasStack& stack, int index) {
    const StackSlice& s = stack.slices.at(std::size_t(index));
    AtlasSliceFrame f;
    f.index = index;
    f.positionUm = s.positionUm;
    f.umPerPx = s.umPerPx;
    f.geometry = s.geometry;
    f.ccf = stack.source.is_object() && stack.source.value("kind", "") == "volume";
    f.stackDir = stack.dir.string();
    f.templateFile = s.templateFile;
    f.idsFile = s.idsFile;
    f.ventricleIds = stack.ventricleIds;
    // The midline: the volume's left-right centre, else the slice's centre column (built-in
    // planes are centred on the brain's axis).
    const json& extent =
        stack.source.is_object() ? stack.source.value("extent_um", json()) : json();
    if (extent.is_array() && extent.size() == 3 && extent[2].is_number())
        f.midlineLrUm = extent[2].get<double>() / 2;
    else
        f.midlineLrUm = s.geometry.atlasUm((s.geometry.size.width - 1) / 2.0,
                                           (s.geometry.size.height - 1) / 2.0)[2];
    return f;
}

json sliceFrameJson(const AtlasSliceFrame& f) {
    return {{"dir", f.stackDir},
            {"index", f.index},
            {"position_um", f.positionUm},
            {"um_per_px", f.umPerPx},
            {"ccf", f.ccf},
            {"midline_lr_um", f.midlineLrUm},
            {"width", f.geometry.size.width},
            {"height", f.geometry.size.height},
            {"origin_um", vec3(f.geometry.originUm)},
            {"column_um", vec3(f.geometry.columnUm)},
            {"row_um", vec3(f.geometry.rowUm)},
            {"normal", vec3(f.geometry.normal)}};
}

core::Result<AtlasSliceFrame> sliceFrameFromJson(const json& j) {
    if (!j.is_object())
        return makeError(ErrorCode::InvalidArgument, "atlas slice frame: expected an object");
    AtlasSliceFrame f;
    auto o = vec3From(j, "origin_um");
    auto c = vec3From(j, "column_um");
    auto r = vec3From(j, "row_um");
    auto n = vec3From(j, "normal");
    for (const auto* v : {&o, &c, &r, &n})
        if (!*v)
            return makeError(ErrorCode::InvalidArgument,
                             "atlas slice frame: " + v->error().message);
    auto index = number(j, "index");
    auto mid = number(j, "midline_lr_um");
    if (!index || !mid || !j.contains("ccf") || !j["ccf"].is_boolean())
        return makeError(
            ErrorCode::InvalidArgument,
            "atlas slice frame: \"index\", \"midline_lr_um\" and \"ccf\" are required");
    f.geometry.originUm = *o;
    f.geometry.columnUm = *c;
    f.geometry.rowUm = *r;
    f.geometry.normal = *n;
    f.geometry.size = {j.value("width", 0), j.value("height", 0)};
    f.index = int(*index);
    f.midlineLrUm = *mid;
    f.ccf = j["ccf"].get<bool>();
    f.positionUm = j.value("position_um", 0.0);
    f.umPerPx = j.value("um_per_px", 0.0);
    f.stackDir = j.value("dir", "");
    f.geometry.positionUm = f.positionUm;
    return f;
}

cv::Vec3d ccfUm(const pipeline::SliceGeometry& slice, cv::Point2d atlasPx) {
    // The atlas frame of a volume stack is micrometres from the first voxel's centre along
    // (AP, DV, LR): Allen's CCF axes, voxel index x voxel size (docs/results.md).
    return slice.atlasUm(atlasPx.x, atlasPx.y);
}

// --- QuickNII / VisuAlign --------------------------------------------------------------------

namespace {
constexpr double kQuickNiiVoxelUm = 25;
}

cv::Vec3d quickNiiFromCcf(cv::Vec3d c) {
    // Voxel centres of the 25 um grid at CCF index x 25; QuickNII's y = 527 - AP index and
    // z = 319 - DV index, continuous with voxel i covering [i, i + 1) (VisuAlign samples voxel
    // int(coordinate)).
    return {c[2] / kQuickNiiVoxelUm + 0.5, kQuickNiiSize[1] - 0.5 - c[0] / kQuickNiiVoxelUm,
            kQuickNiiSize[2] - 0.5 - c[1] / kQuickNiiVoxelUm};
}

cv::Vec3d ccfFromQuickNii(cv::Vec3d q) {
    return {(kQuickNiiSize[1] - 0.5 - q[1]) * kQuickNiiVoxelUm,
            (kQuickNiiSize[2] - 0.5 - q[2]) * kQuickNiiVoxelUm, (q[0] - 0.5) * kQuickNiiVoxelUm};
}

json quickNiiSlice(const std::string& filename, int nr, const SavedMapping& m,
                   const pipeline::SliceGeometry& slice, const QuickNiiOptions& options) {
    const cv::Matx23d A = m.affineAtlasFromImage();
    const double W = m.imageSize.width, H = m.imageSize.height;
    // QuickNII's image coordinates are from the corner: q = p + 0.5.
    auto voxelOfCorner = [&](double qx, double qy) {
        return quickNiiFromCcf(ccfUm(slice, apply(A, {qx - 0.5, qy - 0.5})));
    };
    const cv::Vec3d o = voxelOfCorner(0, 0);
    const cv::Vec3d u = voxelOfCorner(W, 0) - o;
    const cv::Vec3d v = voxelOfCorner(0, H) - o;
    json out{{"filename", filename},
             {"nr", nr},
             {"width", m.imageSize.width},
             {"height", m.imageSize.height},
             {"anchoring", {o[0], o[1], o[2], u[0], u[1], u[2], v[0], v[1], v[2]}}};
    if (options.markerColumns <= 0 || m.dx.empty())
        return out;
    // Markers: dst is where the point is in the image, src where the anchoring's plane must be
    // read so that the affine gives the full map there: A src = full(dst).
    cv::Matx23d inv;
    cv::invertAffineTransform(A, inv);
    const double step = W / options.markerColumns, rowStep = step * std::sqrt(3.0) / 2;
    json markers = json::array();
    int row = 0;
    for (double qy = rowStep / 2; qy < H; qy += rowStep, ++row)
        for (double qx = (row % 2 ? step : step / 2); qx < W; qx += step) {
            const cv::Point2d full = m.atlasFromImage({qx - 0.5, qy - 0.5});
            const cv::Point2d src = apply(inv, full) + cv::Point2d(0.5, 0.5);
            markers.push_back({src.x, src.y, qx, qy});
        }
    out["markers"] = std::move(markers);
    return out;
}

json quickNiiSeries(const std::string& name, json slices) {
    return {{"name", name},
            {"target", kQuickNiiTarget},
            {"target-resolution", {kQuickNiiSize[0], kQuickNiiSize[1], kQuickNiiSize[2]}},
            {"slices", std::move(slices)}};
}

core::Result<VisuAlignMap> VisuAlignMap::create(const json& s, bool useMarkers) {
    auto W = number(s, "width");
    auto H = number(s, "height");
    if (!W || !H || *W < 1 || *H < 1 || *W > 1e6 || *H > 1e6 || !s.contains("anchoring") ||
        !s["anchoring"].is_array() || s["anchoring"].size() != 9)
        return makeError(ErrorCode::InvalidArgument,
                         "QuickNII slice: width, height and 9 anchoring numbers are required");
    VisuAlignMap m;
    m.width_ = *W;
    m.height_ = *H;
    for (int i = 0; i < 9; ++i) {
        if (!s["anchoring"][std::size_t(i)].is_number())
            return makeError(ErrorCode::InvalidArgument, "QuickNII slice: anchoring not numbers");
        m.anchoring_[std::size_t(i)] = s["anchoring"][std::size_t(i)].get<double>();
    }
    const json markers = s.value("markers", json::array());
    if (!useMarkers || !markers.is_array() || markers.empty())
        return m;
    // Delaunay triangulation of the dst points and the fixed corners (VisuAlign's
    // Slice.triangulate); src is interpolated barycentrically in each triangle.
    for (double cy : {0.0, *H})
        for (double cx : {0.0, *W}) {
            m.dst_.push_back({cx, cy});
            m.src_.push_back({cx, cy});
        }
    for (const json& mk : markers) {
        if (!mk.is_array() || mk.size() != 4 || !mk[0].is_number() || !mk[1].is_number() ||
            !mk[2].is_number() || !mk[3].is_number())
            return makeError(ErrorCode::InvalidArgument,
                             "QuickNII slice: a marker is not 4 numbers");
        const cv::Point2d d(mk[2].get<double>(), mk[3].get<double>());
        if (!(d.x > 0 && d.x < *W && d.y > 0 && d.y < *H))
            return makeError(ErrorCode::InvalidArgument,
                             "QuickNII slice: a marker's position lies outside the image");
        m.src_.push_back({mk[0].get<double>(), mk[1].get<double>()});
        m.dst_.push_back(d);
    }
    try {
        cv::Subdiv2D subdiv(cv::Rect(-2, -2, int(*W) + 5, int(*H) + 5));
        std::map<std::pair<float, float>, int> indexOf; // the triangles give back the points
        for (std::size_t i = 0; i < m.dst_.size(); ++i) {
            const cv::Point2f p(float(m.dst_[i].x), float(m.dst_[i].y));
            if (indexOf.emplace(std::pair{p.x, p.y}, int(i)).second)
                subdiv.insert(p);
        }
        std::vector<cv::Vec6f> tris;
        subdiv.getTriangleList(tris);
        for (const cv::Vec6f& t : tris) {
            std::array<int, 3> tri{};
            bool ok = true;
            for (int k = 0; k < 3; ++k) {
                auto it = indexOf.find({t[2 * k], t[2 * k + 1]});
                ok = ok && it != indexOf.end();
                tri[std::size_t(k)] = ok ? it->second : -1;
            }
            if (ok)
                m.triangles_.push_back(tri);
        }
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::InvalidArgument,
                         std::string("QuickNII slice: cannot triangulate the markers: ") +
                             e.what());
    }
    return m;
}

cv::Vec3d VisuAlignMap::voxelOf(cv::Point2d imagePx) const {
    const cv::Point2d q = imagePx + cv::Point2d(0.5, 0.5);
    cv::Point2d src = q; // outside every triangle (off the image): the anchoring alone
    for (const auto& t : triangles_) {
        const cv::Point2d A = dst_[std::size_t(t[0])], B = dst_[std::size_t(t[1])],
                          C = dst_[std::size_t(t[2])];
        const double det = (B.x - A.x) * (C.y - A.y) - (C.x - A.x) * (B.y - A.y);
        if (std::abs(det) < 1e-12)
            continue;
        const double l1 = ((q.x - A.x) * (C.y - A.y) - (C.x - A.x) * (q.y - A.y)) / det;
        const double l2 = ((B.x - A.x) * (q.y - A.y) - (q.x - A.x) * (B.y - A.y)) / det;
        if (l1 < -1e-9 || l2 < -1e-9 || l1 + l2 > 1 + 1e-9)
            continue;
        const cv::Point2d a = src_[std::size_t(t[0])];
        src = a + l1 * (src_[std::size_t(t[1])] - a) + l2 * (src_[std::size_t(t[2])] - a);
        break;
    }
    const double fx = src.x / width_, fy = src.y / height_;
    const auto& an = anchoring_;
    return {an[0] + fx * an[3] + fy * an[6], an[1] + fx * an[4] + fy * an[7],
            an[2] + fx * an[5] + fy * an[8]};
}

core::Result<cv::Vec3d> quickNiiVoxelOf(const json& slice, cv::Point2d imagePx, bool useMarkers) {
    auto m = VisuAlignMap::create(slice, useMarkers);
    if (!m)
        return m.error();
    return m->voxelOf(imagePx);
}

// --- from result.json and the files beside it ---------------------------------------------------

core::Result<SectionFiles> readResultFile(const std::filesystem::path& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in)
        return makeError(std::filesystem::exists(path) ? ErrorCode::IoError : ErrorCode::NotFound,
                         "cannot read " + path.string());
    std::stringstream ss;
    ss << in.rdbuf();
    json j = json::parse(ss.str(), nullptr, false);
    if (j.is_discarded() || !j.is_object())
        return makeError(ErrorCode::InvalidArgument, path.string() + ": not a JSON object");
    return SectionFiles{std::move(j), path.parent_path()};
}

namespace {

core::Result<AtlasSliceFrame> frameOf(const SectionFiles& s) {
    const json& atlas = s.result.value("atlas", json::object());
    if (!atlas.is_object() || !atlas.contains("stack"))
        return makeError(ErrorCode::InvalidArgument,
                         "result: the atlas is not a slice of a stack (\"atlas.stack\" missing); "
                         "register with --atlas STACK --slice N");
    return sliceFrameFromJson(atlas["stack"]);
}

} // namespace

core::Result<json> quickNiiSliceOfResult(const SectionFiles& s, const std::string& filename, int nr,
                                         const QuickNiiOptions& options) {
    auto frame = frameOf(s);
    if (!frame)
        return frame.error();
    if (!frame->ccf)
        return makeError(ErrorCode::InvalidArgument,
                         "the atlas stack was not cut from a CCF volume (e.g. the built-in "
                         "atlas): QuickNII/VisuAlign need CCFv3 coordinates");
    auto mapping = readSavedMapping(s.result, s.resultDir);
    if (!mapping)
        return mapping.error();
    return quickNiiSlice(filename, nr, *mapping, frame->geometry, options);
}

core::Result<json> qupathOfResult(const SectionFiles& s) {
    auto mapping = readSavedMapping(s.result, s.resultDir);
    if (!mapping)
        return mapping.error();
    const json& atlas = s.result.value("atlas", json::object());
    if (!atlas.is_object() || !atlas.contains("file") || !atlas["file"].is_string())
        return makeError(ErrorCode::InvalidArgument, "result: \"atlas.file\" missing");
    auto image = core::readImage(s.resultDir / atlas["file"].get<std::string>());
    if (!image)
        return image.error();
    auto atlasLabels = pipeline::labelsFromImage(*image);
    if (!atlasLabels)
        return atlasLabels.error();
    cv::Mat mx, my;
    mapping->atlasMaps(mapping->imageSize, mx, my);
    // remap has no 32S support; labels go through as float bit patterns untouched by NEAREST.
    cv::Mat asFloat(atlasLabels->size(), CV_32F, atlasLabels->data, atlasLabels->step), out;
    cv::remap(asFloat, out, mx, my, cv::INTER_NEAREST, cv::BORDER_CONSTANT, cv::Scalar(0));
    const cv::Mat labels = cv::Mat(out.size(), CV_32S, out.data, out.step).clone();
    cv::Mat side;
    std::optional<AtlasStack> stack;
    if (auto frame = frameOf(s)) {
        side = pipeline::atlasSideMap(mx, my, frame->geometry, frame->midlineLrUm);
        if (!frame->stackDir.empty())
            if (auto st = readStack(s.resultDir / frame->stackDir))
                stack = std::move(*st);
    }
    // Names: the document's own list (the daemon adds it), else the stack's manifest.
    std::vector<StackRegion> listed;
    if (s.result.contains("regions") && s.result["regions"].is_array())
        for (const json& r : s.result["regions"])
            if (r.is_object() && r.contains("id") && r["id"].is_number_integer()) {
                StackRegion sr{r["id"].get<std::uint32_t>(), r.value("name", std::string()),
                               r.value("acronym", std::string()), 0};
                const std::string c = r.value("color", std::string());
                if (c.size() == 7 && c[0] == '#')
                    sr.colorRgb = std::uint32_t(std::strtoul(c.c_str() + 1, nullptr, 16));
                listed.push_back(std::move(sr));
            }
    RegionLookup lookup = [&](std::uint32_t id) -> const StackRegion* {
        if (stack)
            if (const StackRegion* r = findRegion(*stack, id))
                return r;
        for (const StackRegion& r : listed)
            if (r.id == id)
                return &r;
        return nullptr;
    };
    return qupathFeatures(labels, side, lookup, s.result.value("damage_regions", json::array()));
}

} // namespace slicestation::daemon
