// The page in headless Chromium against a scripted station (tests/web/scripted_station.hpp): the
// test publishes each event when it chooses. The section just flagged is shown even when the
// alert follows its event 2 ms later (the debounce of the old page dropped it); one banner per
// open alert, newest first, each acting on its own alert and section; a pinned section stays
// until the technician lets go; the run controls send what the API expects; the stage position,
// step, focus, damage score, outlines switch, history with local times and the zoomable view.
#include "scripted_station.hpp"
#include "slicestation/daemon/http/http_api.hpp"
#include "webdriver.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdlib>
#include <functional>
#include <string>
#include <thread>
#include <vector>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_web;
using namespace std::chrono_literals;

namespace {

constexpr const char* kToken = "page-token-0123";
const std::filesystem::path kArtefacts =
    std::filesystem::path(SLST_BINARY_DIR) / "test-artefacts" / "web";

bool waitFor(const std::function<bool()>& ready, std::chrono::milliseconds limit = 10s) {
    const auto deadline = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < deadline) {
        if (ready())
            return true;
        std::this_thread::sleep_for(20ms);
    }
    return ready();
}

class PageControl : public ::testing::Test {
protected:
    void SetUp() override {
        // The browser's local time zone: not UTC, so local times are told apart from UTC ones.
        ::setenv("TZ", "Asia/Kolkata", 1);
        auto api = HttpApi::start(station_, "127.0.0.1", 0, kToken);
        ASSERT_TRUE(api) << api.error().message;
        api_ = std::move(*api);
        base_ = "http://127.0.0.1:" + std::to_string(api_->port()) + "/";
    }
    void TearDown() override {
        if (api_)
            api_->stop();
    }
    std::string overlayShown(webdriver::Session& b) {
        auto v = b.execute("const i = document.getElementById('overlay'); "
                           "return i.dataset.sectionId || '';");
        return v.is_string() ? v.get<std::string>() : "";
    }
    /// Publishes a registration event and, `gap` later, the alert the station raises with it.
    void flag(std::int64_t section, std::int64_t alertId, const std::string& raised,
              std::chrono::milliseconds gap) {
        station_.registerSection(section, true, 0.062);
        const auto alert = makeAlert(alertId, section, "damaged", "critical",
                                     "slide-01/s0" + std::to_string(section - 100) +
                                         " is damaged (tear): re-mount it",
                                     raised);
        station_.addAlert(alert);
        station_.publish("section_damaged", {{"section_id", section}, {"run_id", 7}});
        std::this_thread::sleep_for(gap);
        station_.publish("alert_raised", toJson(alert));
    }
    /// Ids of the banners on the page, top first.
    static std::vector<std::string> banners(webdriver::Session& b) {
        return b
            .execute("return [...document.querySelectorAll('#banners .banner')]"
                     ".map(e => e.dataset.alertId);")
            .get<std::vector<std::string>>();
    }
    static std::string bannerButton(std::int64_t alertId, const char* cls) {
        return "#banners .banner[data-alert-id=\"" + std::to_string(alertId) + "\"] " + cls;
    }

    ScriptedStation station_;
    std::unique_ptr<HttpApi> api_;
    std::string base_;
};

} // namespace

TEST_F(PageControl, TheFlaggedSectionIsShownAndEveryBannerActsOnItsOwnSection) {
    webdriver::Session browser(1280, 1000);
    browser.navigate(base_);
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#grid .cell").size() == 4; }));
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("return document.body.dataset.stream;") == "open";
    })) << "the page is on the event stream";

    // s01 registered: shown.
    station_.registerSection(101, false);
    station_.publish("section_registered", {{"section_id", 101}, {"run_id", 7}});
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "101"; }, 3s));

    // s03 flagged, its alert 2 ms later (as the station sends them): s03 is on screen within 1 s.
    const auto t0 = std::chrono::steady_clock::now();
    flag(103, 11, "2026-12-02T09:32:00.000Z", 2ms);
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "103"; }, 1s))
        << "the damaged section is shown within a second of its event; shown: "
        << overlayShown(browser);
    std::cout << "flagged section shown after "
              << std::chrono::duration_cast<std::chrono::milliseconds>(
                     std::chrono::steady_clock::now() - t0)
                     .count()
              << " ms\n";
    EXPECT_NE(browser.text(*browser.find("#overlay-title")).find("DAMAGED"), std::string::npos);

    // A second flagged section (s02): shown in its turn, and there are two banners, newest first.
    flag(102, 12, "2026-12-02T09:33:00.000Z", 2ms);
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "102"; }, 1s));
    ASSERT_TRUE(waitFor([&] {
        return banners(browser) == std::vector<std::string>{"12", "11"};
    })) << "one banner per open alert, newest first";
    // Each banner names its own section and carries its thumbnail.
    for (std::int64_t a : {11, 12}) {
        const std::string sec = a == 11 ? "s03" : "s02";
        const std::string text = browser.text(*browser.find(bannerButton(a, ".banner-text")));
        EXPECT_NE(text.find(sec), std::string::npos) << text;
        const std::string thumb = browser
                                      .execute("return document.querySelector(arguments[0]).src;",
                                               {bannerButton(a, "img.thumb")})
                                      .get<std::string>();
        EXPECT_NE(thumb.find("/api/sections/" + std::to_string(a == 11 ? 103 : 102) + "/"),
                  std::string::npos)
            << thumb;
    }
    // "Show" on the older banner shows its section (s03), and pins it.
    browser.clickCss(bannerButton(11, "button.show"));
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "103"; }, 2s));

    // Acting without the token: the page explains where the token comes from.
    browser.clickCss(bannerButton(11, "button.ack-accept"));
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("return document.getElementById('token-row')"
                               ".classList.contains('shown');") == true;
    })) << "a 401 asks for the token";
    const std::string help = browser.text(*browser.find("#token-help"));
    EXPECT_NE(help.find("daemon.token"), std::string::npos) << help;
    // calls() returns a copy: one copy for both ends of the range.
    const std::vector<std::string> before = station_.calls();
    EXPECT_TRUE(std::none_of(before.begin(), before.end(),
                             [](const std::string& c) { return c.starts_with("ack"); }));
    browser.type(*browser.find("#token"), kToken);
    browser.clickCss("#token-save");

    // Each banner's buttons act on their own alert: accept the newer (s02), rescan the older.
    browser.clickCss(bannerButton(12, "button.ack-accept"));
    ASSERT_TRUE(waitFor([&] { return station_.called("ack accept 12"); }));
    ASSERT_TRUE(waitFor([&] { return banners(browser) == std::vector<std::string>{"11"}; }));
    browser.clickCss(bannerButton(11, "button.ack-rescan"));
    ASSERT_TRUE(waitFor([&] { return station_.called("ack rescan 11"); }));
    ASSERT_TRUE(waitFor([&] { return banners(browser).empty(); }));
    EXPECT_FALSE(station_.called("ack rescan 12"));
    EXPECT_FALSE(station_.called("ack accept 11"));

    // Pinned: a click on s01 keeps s01 on screen while s04 registers; "follow" lets go.
    browser.clickCss("#grid .cell[data-section-id=\"101\"]");
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "101"; }, 2s));
    station_.registerSection(104, false);
    station_.publish("section_registered", {{"section_id", 104}, {"run_id", 7}});
    std::this_thread::sleep_for(700ms);
    EXPECT_EQ(overlayShown(browser), "101") << "a pinned section stays";
    browser.clickCss("#follow");
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "104"; }, 2s))
        << "following again shows the latest registered";
    browser.screenshot(kArtefacts / "page-banners-followed.png");
}

TEST_F(PageControl, RunControlsAndWhatTheTechnicianLooksAt) {
    station_.registerSection(101, false);
    station_.registerSection(103, true, 0.062);
    station_.addAlert(makeAlert(21, 103, "damaged", "critical",
                                "slide-01/s03 is damaged (tear): re-mount it",
                                "2026-12-02T09:32:00.000Z"));
    station_.setStatus("scanning", "moving to s04");
    webdriver::Session browser(1280, 1000);
    browser.navigate(base_);
    browser.execute("localStorage.setItem('slst-token', arguments[0]);", {kToken});
    browser.navigate(base_);
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#grid .cell").size() == 4; }));
    ASSERT_TRUE(
        waitFor([&] { return browser.execute("return document.body.dataset.stream;") == "open"; }));

    // Live: the stage position of the last frame, the step, the focus of the last capture.
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#stage-pos")).find("12345.5") != std::string::npos;
    })) << browser.text(*browser.find("#stage-pos"));
    EXPECT_NE(browser.text(*browser.find("#stage-pos")).find("6789.3"), std::string::npos);
    // While the stage moves, its positions arrive as events and replace it at once.
    station_.publish("stage_position",
                     {{"x_um", 20'500.25}, {"y_um", 3'000}, {"z_um", 2'500}, {"moving", true}});
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#stage-pos")) ==
               "x 20500.3 \u00b5m, y 3000.0 \u00b5m, z 2500.0 \u00b5m (moving)";
    })) << browser.text(*browser.find("#stage-pos"));
    station_.publish("stage_position",
                     {{"x_um", 21'000}, {"y_um", 3'000}, {"z_um", 2'500}, {"moving", false}});
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#stage-pos")).rfind("x 21000.0", 0) == 0 &&
               browser.text(*browser.find("#stage-pos")).find("moving") == std::string::npos;
    })) << browser.text(*browser.find("#stage-pos"));
    EXPECT_EQ(browser.text(*browser.find("#step")), "moving to s04");
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#focus")).find("found, score 0.750") !=
               std::string::npos;
    })) << browser.text(*browser.find("#focus"));
    station_.publish(
        "section_captured",
        {{"section_id", 104}, {"section", "s04"}, {"focus_found", false}, {"focus_score", 0.125}});
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#focus")) == "s04: NOT found, score 0.125";
    })) << browser.text(*browser.find("#focus"));

    // The damage score of the flagged section, in its cell and its detail.
    const std::string cellTitle =
        browser
            .execute("return document.querySelector('#grid .cell[data-section-id=\"103\"]').title;")
            .get<std::string>();
    EXPECT_NE(cellTitle.find("damage 6.2%"), std::string::npos) << cellTitle;
    browser.clickCss("#grid .cell[data-section-id=\"103\"]");
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#detail")).find("6.2% of the section") !=
               std::string::npos;
    })) << browser.text(*browser.find("#detail"));

    // Outlines off: the plain image; on: the overlay.
    ASSERT_TRUE(waitFor([&] { return overlayShown(browser) == "103"; }, 2s));
    auto src = [&] {
        return browser.execute("return document.getElementById('overlay').src;").get<std::string>();
    };
    EXPECT_NE(src().find("/api/sections/103/overlay.png"), std::string::npos) << src();
    browser.clickCss("#outlines");
    ASSERT_TRUE(
        waitFor([&] { return src().find("/api/sections/103/image.jpg") != std::string::npos; }, 2s))
        << src();
    browser.clickCss("#outlines");
    ASSERT_TRUE(waitFor(
        [&] { return src().find("/api/sections/103/overlay.png") != std::string::npos; }, 2s));

    // Zoom: the full-resolution image (2400 px, not the 1024 px view), magnified by the button.
    browser.clickCss("#zoom-open");
    ASSERT_TRUE(waitFor([&] {
        return browser.execute(
                   "const i = document.getElementById('zoom-img'); "
                   "return i.complete && i.dataset.fitted === 'yes' && i.naturalWidth;") == 2400;
    })) << "the zoomed view reads the image at full resolution";
    const double scale0 =
        std::stod(browser.execute("return document.getElementById('zoom-img').dataset.scale;")
                      .get<std::string>());
    browser.clickCss("#zoom-in");
    browser.clickCss("#zoom-in");
    const double scale2 =
        std::stod(browser.execute("return document.getElementById('zoom-img').dataset.scale;")
                      .get<std::string>());
    EXPECT_NEAR(scale2 / scale0, 2.25, 1e-6) << "each step magnifies 1.5 times";
    browser.screenshot(kArtefacts / "page-zoom.png");
    browser.clickCss("#zoom-close");

    // With outlines off the zoom draws tiles of the image's pyramid: zoomed in, full-resolution
    // tiles (level 0) cover the view; the one under the frame's centre is the tile the view's
    // geometry asks for, fetched from the tile route and drawn with its own pixels.
    browser.clickCss("#outlines");
    ASSERT_TRUE(waitFor(
        [&] { return src().find("/api/sections/103/image.jpg") != std::string::npos; }, 2s));
    browser.clickCss("#zoom-open");
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("const i = document.getElementById('zoom-img'); "
                               "return i.complete && i.dataset.fitted === 'yes';") == true;
    }));
    for (int i = 0; i < 3; ++i)
        browser.clickCss("#zoom-in");
    // The tile under the centre: its key from the page's own transform, its pixel from a canvas.
    const char* centreTile = R"(
        const f = document.getElementById('zoom-frame').getBoundingClientRect();
        const cx = f.left + f.width / 2, cy = f.top + f.height / 2;
        for (const t of document.querySelectorAll('#zoom-tiles img.tile')) {
          const r = t.getBoundingClientRect();
          if (t.dataset.drawn !== 'yes' || cx < r.left || cx >= r.right || cy < r.top || cy >= r.bottom) continue;
          const c = document.createElement('canvas'); c.width = 1; c.height = 1;
          const g = c.getContext('2d'); g.drawImage(t, 5, 5, 1, 1, 0, 0, 1, 1);
          const d = g.getImageData(0, 0, 1, 1).data;
          const img = document.getElementById('zoom-img');
          const s = parseFloat(img.dataset.scale) * img.naturalWidth / 2400;
          const m = /translate\(([-0-9.e]+)px, *([-0-9.e]+)px\)/.exec(img.style.transform);
          const fx = (cx - f.left - parseFloat(m[1])) / s, fy = (cy - f.top - parseFloat(m[2])) / s;
          return {key: t.dataset.key, rgb: [d[0], d[1], d[2]],
                  expected: t.dataset.level + '/' + Math.floor(fx / 512 / (1 << +t.dataset.level)) + '_' +
                            Math.floor(fy / 512 / (1 << +t.dataset.level))};
        }
        return null;)";
    nlohmann::json centre;
    ASSERT_TRUE(waitFor([&] {
        centre = browser.execute(centreTile);
        return centre.is_object() && centre["key"].get<std::string>().rfind("0/", 0) == 0;
    })) << "a full-resolution tile is drawn under the centre; got "
        << centre.dump() << ", level " << browser.text(*browser.find("#zoom-level"));
    EXPECT_EQ(centre["key"], centre["expected"]) << centre.dump();
    const std::string key = centre["key"];
    const int tx = std::stoi(key.substr(2, key.find('_') - 2));
    const int ty = std::stoi(key.substr(key.find('_') + 1));
    EXPECT_TRUE(station_.called("tile 103 " + key)) << "fetched from the tile route";
    EXPECT_EQ(centre["rgb"], nlohmann::json::array({250, 20 + 40 * ty, 20 + 40 * tx}))
        << "the tile's own pixels are drawn";
    EXPECT_NE(browser.text(*browser.find("#zoom-level")).find("level 0"), std::string::npos);
    browser.screenshot(kArtefacts / "page-zoom-tiles.png");
    // Zoomed out to a quarter of full resolution: the reduced level replaces them.
    for (int i = 0; i < 6; ++i)
        browser.clickCss("#zoom-out");
    ASSERT_TRUE(waitFor([&] {
        return browser.execute("return document.querySelectorAll('#zoom-tiles "
                               "img.tile[data-level=\"1\"][data-drawn=\"yes\"]').length > 0 && "
                               "document.querySelectorAll('#zoom-tiles "
                               "img.tile[data-level=\"0\"]').length === 0;") == true;
    })) << browser.text(*browser.find("#zoom-level"));
    EXPECT_TRUE(station_.called("tile 103 1/0_0"));
    browser.screenshot(kArtefacts / "page-zoom-tiles-level1.png");
    browser.clickCss("#zoom-close");
    browser.clickCss("#outlines");

    // History: both runs, times in the browser's local time zone (UTC+5:30 here), labelled.
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#history tr[data-run-id]").size() == 2; }));
    const std::string history = browser.text(*browser.find("#history"));
    EXPECT_NE(history.find("15:00"), std::string::npos) << "09:30 UTC is 15:00 in Kolkata\n"
                                                        << history;
    EXPECT_NE(browser.text(*browser.find("#tz")).find("(UTC+05:30)"), std::string::npos)
        << browser.text(*browser.find("#tz"));
    const std::string alertsText = browser.text(*browser.find("#alerts"));
    EXPECT_NE(alertsText.find("15:02"), std::string::npos) << alertsText;

    // Section controls: rescan; accept answers the section's open alert.
    browser.clickCss("#sec-accept");
    ASSERT_TRUE(waitFor([&] { return station_.called("ack accept 21"); }));
    browser.clickCss("#sec-rescan");
    ASSERT_TRUE(waitFor([&] { return station_.called("rescan 103"); }));

    // Run controls, each the request the API documents; the buttons follow the run's state.
    auto enabled = [&](const char* id) {
        return browser.execute("return !document.getElementById(arguments[0]).disabled;", {id}) ==
               true;
    };
    ASSERT_TRUE(waitFor([&] { return enabled("ctl-pause"); }));
    EXPECT_FALSE(enabled("ctl-resume"));
    browser.clickCss("#ctl-pause");
    ASSERT_TRUE(waitFor([&] { return station_.called("pause 7"); }));
    station_.publish("run_state", {{"run_id", 7}, {"state", "paused"}});
    ASSERT_TRUE(waitFor([&] { return enabled("ctl-resume") && !enabled("ctl-pause"); }));
    browser.clickCss("#ctl-reset-resume");
    ASSERT_TRUE(waitFor([&] { return station_.called("resume reset 7"); }));
    station_.publish("run_state", {{"run_id", 7}, {"state", "running"}});
    ASSERT_TRUE(waitFor([&] { return enabled("ctl-pause"); }));
    browser.clickCss("#ctl-pause");
    ASSERT_TRUE(waitFor([&] {
        auto cs = station_.calls();
        return std::count(cs.begin(), cs.end(), "pause 7") == 2;
    }));
    station_.publish("run_state", {{"run_id", 7}, {"state", "paused"}});
    ASSERT_TRUE(waitFor([&] { return enabled("ctl-resume"); }));
    browser.clickCss("#ctl-resume");
    ASSERT_TRUE(waitFor([&] { return station_.called("resume 7"); }));
    browser.screenshot(kArtefacts / "page-controls.png");
    // Cancel asks once more before it goes.
    browser.clickCss("#ctl-cancel");
    EXPECT_FALSE(station_.called("cancel 7")) << "one click does not cancel a run";
    browser.clickCss("#ctl-cancel-confirm");
    ASSERT_TRUE(waitFor([&] { return station_.called("cancel 7"); }));

    // On a phone nothing is wider than the page (the history table and the banners included).
    browser.resize(390, 844);
    ASSERT_TRUE(
        waitFor([&] { return browser.execute("return window.innerWidth;").get<int>() <= 420; }));
    EXPECT_EQ(browser.execute(
                  "const d = document.documentElement; return d.scrollWidth <= d.clientWidth;"),
              true)
        << browser.execute(
               "const d = document.documentElement; return [d.scrollWidth, d.clientWidth, "
               "[...document.querySelectorAll('body *')].filter(e => "
               "e.getBoundingClientRect().right > d.clientWidth + 0.5).slice(0, 8)"
               ".map(e => e.tagName + '#' + e.id + '.' + e.className + ' ' + "
               "Math.round(e.getBoundingClientRect().right))];");
}

// Issue 18: a damage banner shows the section's score, a "check the registration" banner is a
// warning with its own wording, and the section panel shows verdict, score, the flag score it was
// judged at and each region's score.
TEST_F(PageControl, DamageBannersAndTheSectionPanelShowTheScoreAndTheVerdict) {
    webdriver::Session browser(1280, 1000);
    browser.navigate(base_);
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#grid .cell").size() == 4; }));
    ASSERT_TRUE(
        waitFor([&] { return browser.execute("return document.body.dataset.stream;") == "open"; }));
    station_.registerSection(103, true, 0.031, 0.83, "damaged");
    const auto torn = makeAlert(21, 103, "damaged", "critical",
                                "section s03 (slide-01, run 7) is damaged, score 0.83: 1 tear "
                                "(3.1% of the tissue): re-mount it and request a rescan, or "
                                "accept it as is",
                                "2026-12-02T09:32:00.000Z");
    station_.addAlert(torn);
    station_.publish("section_damaged", {{"section_id", 103}, {"run_id", 7}});
    station_.publish("alert_raised", toJson(torn));
    station_.registerSection(102, false, 0.02, 0.62, "check_registration");
    const auto check = makeAlert(22, 102, "check_registration", "warning",
                                 "check the registration of section s02 (slide-01, run 7): "
                                 "tissue looks missing where the atlas fit is uncertain (score "
                                 "0.62: 1 missing (2.0% of the tissue))",
                                 "2026-12-02T09:33:00.000Z");
    station_.addAlert(check);
    station_.publish("section_check_registration", {{"section_id", 102}, {"run_id", 7}});
    station_.publish("alert_raised", toJson(check));
    ASSERT_TRUE(waitFor([&] {
        return banners(browser) == std::vector<std::string>{"22", "21"};
    })) << "both banners";

    const auto scoreOf = [&](std::int64_t alert) {
        auto e = browser.find(bannerButton(alert, ".banner-score"));
        return e ? browser.text(*e) : std::string("(no score)");
    };
    ASSERT_TRUE(waitFor([&] { return scoreOf(21) == "score 0.83"; })) << scoreOf(21);
    EXPECT_EQ(scoreOf(22), "score 0.62");
    EXPECT_EQ(
        browser.execute("return document.querySelector('#banners .banner[data-alert-id=\"22\"]')"
                        ".className;"),
        "banner warning");
    EXPECT_NE(
        browser.text(*browser.find(bannerButton(22, ".banner-text"))).find("check registration"),
        std::string::npos);

    browser.clickCss(bannerButton(21, "button.show"));
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#detail"))
                   .find("damaged, score 0.83 (flagged from 0.50)") != std::string::npos;
    })) << browser.text(*browser.find("#detail"));
    EXPECT_NE(browser.text(*browser.find("#detail")).find("tear, 3.1% of the section, score 0.71"),
              std::string::npos)
        << browser.text(*browser.find("#detail"));
    browser.clickCss(bannerButton(22, "button.show"));
    ASSERT_TRUE(waitFor([&] {
        return browser.text(*browser.find("#detail")).find("check the registration, score 0.62") !=
               std::string::npos;
    })) << browser.text(*browser.find("#detail"));
    std::filesystem::create_directories(kArtefacts);
    browser.screenshot(kArtefacts / "page-damage-score.png");
}

TEST_F(PageControl, TheSectionDetailAndTheRunShowCellsPerRegion) {
    // COUNTS.csv as the station writes it (docs/cells.md): every ancestor summed, names quoted
    // where they hold a comma.
    const std::string head = "id,acronym,name,parent_id,depth,count,area_mm2,density_per_mm2\n";
    station_.setCounts(101, head + "997,root,root,,0,450,6,75\n"
                                   "8,grey,Basic cell groups and regions,997,1,430,5.5,78.18\n"
                                   "315,Isocortex,Isocortex,8,2,250,2.5,100\n"
                                   "549,TH,Thalamus,8,2,150,1.5,100\n"
                                   "485,STRd,\"Striatum, dorsal region\",8,2,30,1.5,20\n"
                                   "1009,fiber tracts,fiber tracts,997,1,20,0.5,40\n");
    station_.setRunCounts(head + "997,root,root,,0,1210,12,100.83\n"
                                 "8,grey,Basic cell groups and regions,997,1,1170,11,106.36\n"
                                 "315,Isocortex,Isocortex,8,2,700,5,140\n"
                                 "549,TH,Thalamus,8,2,470,6,78.33\n"
                                 "1009,fiber tracts,fiber tracts,997,1,40,1,40\n");
    station_.registerSection(101, false);
    station_.registerSection(103, false);   // registered, not counted
    webdriver::Session browser(1280, 1500); // tall: the run's and the section's tables in one shot
    browser.navigate(base_);
    ASSERT_TRUE(waitFor([&] { return browser.findAll("#grid .cell").size() == 4; }));
    ASSERT_TRUE(
        waitFor([&] { return browser.execute("return document.body.dataset.stream;") == "open"; }));
    auto rows = [&](const std::string& table) {
        return browser
            .execute("return [...document.querySelectorAll(arguments[0] + ' tr')].slice(1)"
                     ".map(r => [...r.children].map(c => c.textContent));",
                     {table})
            .get<std::vector<std::vector<std::string>>>();
    };

    // The run's totals under the grid: the finest regions, most cells first, then the total.
    ASSERT_TRUE(waitFor([&] { return browser.find("#run-counts-table").has_value(); }))
        << "the run's counts are shown";
    auto run = rows("#run-counts-table");
    ASSERT_EQ(run.size(), 4u);
    EXPECT_EQ(run[0], (std::vector<std::string>{"Isocortex (Isocortex)", "700", "140"}));
    EXPECT_EQ(run[1], (std::vector<std::string>{"Thalamus (TH)", "470", "78"}));
    EXPECT_EQ(run[2][0], "fiber tracts (fiber tracts)");
    EXPECT_EQ(run[3], (std::vector<std::string>{"All regions", "1,210", "101"}));

    // A section's detail: its own top regions (the quoted name read whole) and its total.
    browser.clickCss("#grid .cell[data-section-id=\"101\"]");
    ASSERT_TRUE(waitFor([&] { return browser.find("#sec-counts-table").has_value(); }));
    auto sec = rows("#sec-counts-table");
    ASSERT_EQ(sec.size(), 5u);
    EXPECT_EQ(sec[0], (std::vector<std::string>{"Isocortex (Isocortex)", "250", "100"}));
    EXPECT_EQ(sec[2], (std::vector<std::string>{"Striatum, dorsal region (STRd)", "30", "20"}));
    EXPECT_EQ(sec[4], (std::vector<std::string>{"All regions", "450", "75"}));
    browser.screenshot(kArtefacts / "page-cell-counts.png");

    // A registered section without counts (counting off, or not done yet): no table...
    browser.clickCss("#grid .cell[data-section-id=\"103\"]");
    ASSERT_TRUE(waitFor(
        [&] { return browser.text(*browser.find("#detail")).find("s03") != std::string::npos; }));
    EXPECT_FALSE(browser.find("#sec-counts-table").has_value());
    // ...until the station publishes that it counted it: the open detail shows them at once.
    station_.setCounts(103,
                       head + "997,root,root,,0,12,1,12\n315,Isocortex,Isocortex,997,1,12,1,12\n");
    station_.publish("cells_counted", {{"section_id", 103}, {"run_id", 7}, {"counted", 12}});
    ASSERT_TRUE(waitFor([&] { return browser.find("#sec-counts-table").has_value(); }, 3s))
        << "the counts appear when the station publishes them";
    EXPECT_EQ(rows("#sec-counts-table").back(),
              (std::vector<std::string>{"All regions", "12", "12"}));
}
