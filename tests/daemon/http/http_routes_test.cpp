// The HTTP API's routes alone, over a fake station (no devices, no journal, no scan loop): what
// each resource answers, and the one table from station errors to statuses.
#include "slicestation/daemon/http/http_api.hpp"
#include "slicestation/daemon/station/station_api.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <opencv2/imgcodecs.hpp>

#include <map>
#include <mutex>
#include <string>
#include <vector>

using namespace slicestation;
using namespace slicestation::daemon;
using core::ErrorCode;
using core::makeError;

namespace {

constexpr const char* kToken = "fake-token";

/// Answers from fixed records; each control call is recorded, and `fail` makes the next call of
/// that name fail with the given error.
class FakeStation final : public StationApi {
public:
    std::map<std::string, core::Error> fail;
    std::vector<std::string> calls;
    std::vector<std::function<void(const StationEvent&)>> listeners;
    cv::Mat image = cv::Mat(40, 60, CV_16UC1, cv::Scalar(1000));

    nlohmann::json status() override { return {{"state", "idle"}}; }
    core::Result<std::vector<RunRecord>> runs() override {
        if (auto e = failing("runs"))
            return *e;
        RunRecord r;
        r.id = 7;
        r.name = "mouse-42";
        return std::vector<RunRecord>{r};
    }
    core::Result<RunRecord> run(std::int64_t id) override {
        if (id != 7)
            return makeError(ErrorCode::NotFound, "no run " + std::to_string(id));
        RunRecord r;
        r.id = 7;
        r.plan = {{"name", "mouse-42"}};
        return r;
    }
    core::Result<std::vector<SectionRecord>> sections(std::int64_t id) override {
        if (id != 7)
            return makeError(ErrorCode::NotFound, "no run " + std::to_string(id));
        return std::vector<SectionRecord>(2);
    }
    core::Result<std::string> exportRun(std::int64_t, const std::string& format) override {
        if (format != "json" && format != "csv")
            return makeError(ErrorCode::InvalidArgument, "format");
        return std::string(format == "csv" ? "a,b\n" : "{}\n");
    }
    core::Result<nlohmann::json> sectionDetail(std::int64_t id) override {
        if (auto e = failing("sectionDetail"))
            return *e;
        return nlohmann::json{{"id", id}};
    }
    core::Result<std::vector<AlertRecord>> alerts(bool openOnly) override {
        calls.push_back(openOnly ? "alerts open" : "alerts all");
        return std::vector<AlertRecord>{};
    }
    std::shared_ptr<const hw::Frame> frame; ///< the live frame; none until a test sets one
    std::shared_ptr<const hw::Frame> liveFrame() const override { return frame; }
    core::Result<cv::Mat> sectionImage(std::int64_t id, bool overlay) override {
        if (auto e = failing("sectionImage"))
            return *e;
        calls.push_back("image " + std::to_string(id) + (overlay ? " overlay" : ""));
        return image;
    }
    core::Result<RegionAtPixel> regionAt(std::int64_t, int x, int y, int ofWidth) override {
        if (auto e = failing("regionAt"))
            return *e;
        calls.push_back("region " + std::to_string(x) + "," + std::to_string(y) + " of " +
                        std::to_string(ofWidth));
        return RegionAtPixel{315, x, y, "Isocortex", "Isocortex"};
    }
    core::Result<std::int64_t> submitPlan(const nlohmann::json& plan, const std::string&) override {
        if (auto e = failing("submitPlan"))
            return *e;
        calls.push_back("submit " + plan.value("name", std::string()));
        return std::int64_t{8};
    }
    core::Result<void> pauseRun(std::int64_t id) override { return control("pause", id); }
    core::Result<void> resumeRun(std::int64_t id, bool reset) override {
        return control(reset ? "resume reset" : "resume", id);
    }
    core::Result<void> cancelRun(std::int64_t id) override { return control("cancel", id); }
    core::Result<void> requestRescan(std::int64_t id) override { return control("rescan", id); }
    core::Result<AlertRecord> acknowledgeAlert(std::int64_t id,
                                               const std::string& action) override {
        if (auto r = control("ack " + action, id); !r)
            return r.error();
        AlertRecord a;
        a.id = id;
        a.ackAction = action;
        return a;
    }
    void addListener(std::function<void(const StationEvent&)> l) override {
        listeners.push_back(std::move(l));
    }

private:
    std::optional<core::Error> failing(const std::string& name) {
        auto it = fail.find(name);
        if (it == fail.end())
            return std::nullopt;
        auto e = it->second;
        fail.erase(it);
        return e;
    }
    core::Result<void> control(const std::string& name, std::int64_t id) {
        const std::string key = name.substr(0, name.find(' '));
        if (auto e = failing(key))
            return *e;
        calls.push_back(name + " " + std::to_string(id));
        return {};
    }
};

class HttpRoutes : public ::testing::Test {
protected:
    void SetUp() override {
        auto api = HttpApi::start(station_, "127.0.0.1", 0, kToken);
        ASSERT_TRUE(api) << api.error().message;
        api_ = std::move(*api);
        client_ = std::make_unique<httplib::Client>("127.0.0.1", api_->port());
    }
    httplib::Result post(const std::string& path, const std::string& body = "",
                         const std::string& type = "application/json") {
        return client_->Post(path.c_str(), {{"Authorization", std::string("Bearer ") + kToken}},
                             body, type.c_str());
    }
    static std::string errorOf(const httplib::Result& r) {
        auto j = nlohmann::json::parse(r->body, nullptr, false);
        return j.is_object() ? j.value("error", std::string()) : std::string();
    }
    FakeStation station_;
    std::unique_ptr<HttpApi> api_;
    std::unique_ptr<httplib::Client> client_;
};

TEST_F(HttpRoutes, ReadsAnswerFromTheStation) {
    auto runs = client_->Get("/api/runs");
    ASSERT_TRUE(runs);
    EXPECT_EQ(runs->status, 200);
    EXPECT_EQ(nlohmann::json::parse(runs->body)[0]["name"], "mouse-42");
    auto run = client_->Get("/api/runs/7");
    ASSERT_TRUE(run);
    EXPECT_EQ(nlohmann::json::parse(run->body)["plan"]["name"], "mouse-42");
    EXPECT_EQ(nlohmann::json::parse(client_->Get("/api/runs/7/sections")->body).size(), 2u);
    auto csv = client_->Get("/api/runs/7/export?format=csv");
    EXPECT_EQ(csv->body, "a,b\n");
    EXPECT_EQ(csv->get_header_value("Content-Type"), "text/csv");
    EXPECT_EQ(client_->Get("/api/alerts?open=1")->status, 200);
    EXPECT_EQ(station_.calls.back(), "alerts open");
    EXPECT_EQ(nlohmann::json::parse(client_->Get("/api/status")->body)["state"], "idle");
}

TEST_F(HttpRoutes, StatusCarriesTheStagePositionOfTheLatestFrame) {
    auto status = nlohmann::json::parse(client_->Get("/api/status")->body);
    EXPECT_FALSE(status.contains("stage")) << "no frame yet: no position";
    auto f = std::make_shared<hw::Frame>(hw::PixelFormat::Mono8, 4, 4);
    station_.frame = f;
    status = nlohmann::json::parse(client_->Get("/api/status")->body);
    EXPECT_FALSE(status.contains("stage")) << "a frame whose position the camera did not know";
    auto g = std::make_shared<hw::Frame>(hw::PixelFormat::Mono8, 4, 4);
    g->metadata.stage = hw::StagePosition{1.5, -2.25, 300};
    station_.frame = g;
    status = nlohmann::json::parse(client_->Get("/api/status")->body);
    EXPECT_EQ(status["stage"], (nlohmann::json{{"x_um", 1.5}, {"y_um", -2.25}, {"z_um", 300.0}}));
    EXPECT_EQ(status["state"], "idle");
}

TEST_F(HttpRoutes, ImagesAreStretchedScaledAndEncoded) {
    auto jpg = client_->Get("/api/sections/3/image.jpg?width=30");
    ASSERT_TRUE(jpg);
    ASSERT_EQ(jpg->status, 200);
    EXPECT_EQ(jpg->get_header_value("Content-Type"), "image/jpeg");
    const cv::Mat shown =
        cv::imdecode(std::vector<uchar>(jpg->body.begin(), jpg->body.end()), cv::IMREAD_UNCHANGED);
    EXPECT_EQ(shown.cols, 30); // 60 px scaled to 30, never up
    EXPECT_EQ(shown.rows, 20);
    EXPECT_EQ(shown.depth(), CV_8U);
    EXPECT_EQ(station_.calls.back(), "image 3");
    auto png = client_->Get("/api/sections/3/overlay.png?width=4096");
    ASSERT_EQ(png->status, 200);
    EXPECT_EQ(station_.calls.back(), "image 3 overlay");
    EXPECT_EQ(client_->Get("/api/sections/3/image.jpg?width=9")->status, 400) << "width below 16";
    EXPECT_EQ(client_->Get("/api/live.jpg")->status, 404) << "no frame yet";
}

TEST_F(HttpRoutes, RegionLookupPassesThePixelAndTheShownWidth) {
    auto r = client_->Get("/api/sections/3/region?x=10&y=12&of_width=600");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200);
    const auto j = nlohmann::json::parse(r->body);
    EXPECT_EQ(j["id"], 315);
    EXPECT_EQ(j["acronym"], "Isocortex");
    EXPECT_EQ(station_.calls.back(), "region 10,12 of 600");
    EXPECT_EQ(client_->Get("/api/sections/3/region?x=10")->status, 400) << "y missing";
    station_.fail["regionAt"] =
        makeError(ErrorCode::InvalidArgument, "x, y: outside the 60x40 image");
    auto outside = client_->Get("/api/sections/3/region?x=100&y=1");
    EXPECT_EQ(outside->status, 400);
    EXPECT_EQ(errorOf(outside), "x, y: outside the 60x40 image");
}

TEST_F(HttpRoutes, OneTableMapsStationErrorsToStatuses) {
    // Reads: InvalidArgument 400, NotFound 404, a station fault 500.
    const std::vector<std::pair<ErrorCode, int>> reads = {{ErrorCode::InvalidArgument, 400},
                                                          {ErrorCode::OutOfRange, 400},
                                                          {ErrorCode::NotFound, 404},
                                                          {ErrorCode::IoError, 500},
                                                          {ErrorCode::Internal, 500}};
    for (const auto& [code, status] : reads) {
        station_.fail["sectionDetail"] = makeError(code, "why");
        auto r = client_->Get("/api/sections/5");
        ASSERT_TRUE(r);
        EXPECT_EQ(r->status, status) << core::toString(code);
        EXPECT_EQ(errorOf(r), "why");
    }
    // Controls: InvalidArgument means "not in a state for it": 409.
    const std::vector<std::pair<ErrorCode, int>> controls = {{ErrorCode::InvalidArgument, 409},
                                                             {ErrorCode::OutOfRange, 400},
                                                             {ErrorCode::NotFound, 404},
                                                             {ErrorCode::IoError, 500}};
    for (const auto& [code, status] : controls)
        for (const char* action : {"pause", "resume", "cancel"}) {
            station_.fail[action] = makeError(code, "why");
            auto r = post(std::string("/api/runs/7/") + action);
            ASSERT_TRUE(r);
            EXPECT_EQ(r->status, status) << action << " " << core::toString(code);
        }
    station_.fail["rescan"] = makeError(ErrorCode::InvalidArgument, "section 5 is queued");
    EXPECT_EQ(post("/api/sections/5/rescan")->status, 409);
    station_.fail["ack"] = makeError(ErrorCode::NotFound, "no alert 9");
    EXPECT_EQ(post("/api/alerts/9/ack")->status, 404);
    // A plan the station refuses is the request's fault; a journal that cannot store it is not.
    station_.fail["submitPlan"] =
        makeError(ErrorCode::InvalidArgument, "slides[0].sections[0].x_um: missing");
    EXPECT_EQ(post("/api/runs", R"({"name": "x"})")->status, 400);
    station_.fail["submitPlan"] = makeError(ErrorCode::IoError, "database or disk is full");
    EXPECT_EQ(post("/api/runs", R"({"name": "x"})")->status, 500);
}

TEST_F(HttpRoutes, ControlsNeedTheTokenAndReachTheStation) {
    auto anonymous = client_->Post("/api/runs/7/pause", "", "application/json");
    ASSERT_TRUE(anonymous);
    EXPECT_EQ(anonymous->status, 401);
    EXPECT_TRUE(station_.calls.empty());

    EXPECT_EQ(post("/api/runs/7/pause")->status, 200);
    EXPECT_EQ(post("/api/runs/7/resume", R"({"reset_stage_alarm": true})")->status, 200);
    EXPECT_EQ(post("/api/runs/7/resume", R"({"reset_stage_alarm": "yes"})")->status, 400);
    EXPECT_EQ(post("/api/runs/7/cancel")->status, 200);
    EXPECT_EQ(post("/api/sections/5/rescan")->status, 200);
    auto ack = post("/api/alerts/9/ack", R"({"action": "rescan"})");
    ASSERT_EQ(ack->status, 200);
    EXPECT_EQ(nlohmann::json::parse(ack->body)["ack_action"], "rescan");
    auto plan = post("/api/runs", "name = \"toml plan\"\n", "application/toml");
    ASSERT_EQ(plan->status, 201);
    EXPECT_EQ(nlohmann::json::parse(plan->body)["run_id"], 8);
    EXPECT_EQ(post("/api/runs", "name = ")->status, 400) << "a TOML syntax error";
    const std::vector<std::string> expected = {"pause 7",  "resume reset 7", "cancel 7",
                                               "rescan 5", "ack rescan 9",   "submit toml plan"};
    EXPECT_EQ(station_.calls, expected);
}

TEST_F(HttpRoutes, EventsReachTheStreamAsServerSentEvents) {
    ASSERT_EQ(station_.listeners.size(), 1u) << "the API listens to the station once";
    std::string received;
    std::mutex mutex;
    std::thread reader([&] {
        httplib::Client c("127.0.0.1", api_->port());
        c.set_read_timeout(5, 0);
        c.Get("/api/events", [&](const char* data, std::size_t n) {
            std::lock_guard lock(mutex);
            received.append(data, n);
            return received.find("section_captured") == std::string::npos;
        });
    });
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    bool seen = false;
    while (!seen && std::chrono::steady_clock::now() < until) {
        station_.listeners[0]({"section_captured", {{"section_id", 5}}});
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        std::lock_guard lock(mutex);
        seen =
            received.find("event: section_captured\ndata: {\"section_id\":5}") != std::string::npos;
    }
    reader.join();
    EXPECT_TRUE(seen) << received;
}

} // namespace
