#pragma once
// A minimal W3C WebDriver client for the browser tests: starts Debian's chromedriver on a free
// loopback port, opens one headless Chromium session and speaks the protocol over cpp-httplib.
// Only what the page tests use: navigate, find, text/attribute, click, type, execute script,
// pointer move, window size, screenshot.
#include <httplib.h>
#include <nlohmann/json.hpp>
#include <openssl/evp.h>

#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

extern char** environ;

namespace slicestation::webdriver {

inline constexpr const char* kElementKey = "element-6066-11e4-a52e-4f735466cecf";

/// Script arguments: one element.
inline nlohmann::json elementArg(const std::string& element) {
    return nlohmann::json::array({nlohmann::json{{kElementKey, element}}});
}

/// A port nobody listens on right now (bound and released; good enough on loopback in a test).
inline int freePort() {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof a;
    if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
        ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0)
        throw std::runtime_error("no free port");
    const int port = ntohs(a.sin_port);
    ::close(fd);
    return port;
}

/// Decodes base64 (the screenshot WebDriver sends) with OpenSSL's EVP_DecodeBlock.
inline std::vector<unsigned char> base64Decode(const std::string& in) {
    std::vector<unsigned char> out(3 * (in.size() / 4) + 3);
    const int n = EVP_DecodeBlock(out.data(), reinterpret_cast<const unsigned char*>(in.data()),
                                  static_cast<int>(in.size()));
    if (n < 0)
        throw std::runtime_error("WebDriver: the screenshot is not base64");
    // EVP_DecodeBlock counts the bytes the '=' padding stands for; they are not data.
    std::size_t size = static_cast<std::size_t>(n);
    for (auto it = in.rbegin(); it != in.rend() && *it == '=' && size > 0; ++it)
        --size;
    out.resize(size);
    return out;
}

class Session {
public:
    /// Starts chromedriver and a headless Chromium session; throws with the reason otherwise.
    Session(int width, int height) {
        const char* driver = "/usr/bin/chromedriver";
        if (!std::filesystem::exists(driver))
            throw std::runtime_error("chromedriver not installed (Debian package chromium-driver; "
                                     "scripts/install-deps.sh installs it)");
        port_ = freePort();
        const std::string portArg = "--port=" + std::to_string(port_);
        std::vector<char*> argv{const_cast<char*>(driver), const_cast<char*>(portArg.c_str()),
                                nullptr};
        if (::posix_spawn(&pid_, driver, nullptr, nullptr, argv.data(), environ) != 0)
            throw std::runtime_error("cannot start chromedriver");
        http_ = std::make_unique<httplib::Client>("127.0.0.1", port_);
        http_->set_read_timeout(60, 0);
        const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
        while (!http_->Get("/status")) {
            if (std::chrono::steady_clock::now() > deadline)
                throw std::runtime_error("chromedriver did not start");
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
        }
        nlohmann::json args = {
            "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
            "--window-size=" + std::to_string(width) + "," + std::to_string(height)};
        nlohmann::json caps = {
            {"capabilities",
             {{"alwaysMatch",
               {{"browserName", "chrome"},
                {"goog:chromeOptions", {{"binary", "/usr/bin/chromium"}, {"args", args}}}}}}}};
        auto r = call("POST", "/session", caps);
        session_ = r["sessionId"].get<std::string>();
    }
    ~Session() {
        if (!session_.empty())
            (void)http_->Delete("/session/" + session_);
        if (pid_ > 0) {
            ::kill(pid_, SIGTERM);
            int st = 0;
            ::waitpid(pid_, &st, 0);
        }
    }
    Session(const Session&) = delete;
    Session& operator=(const Session&) = delete;

    void navigate(const std::string& url) { call("POST", path("/url"), {{"url", url}}); }
    /// The first element matching the CSS selector, or nullopt.
    std::optional<std::string> find(const std::string& css) {
        auto r = raw("POST", path("/element"), {{"using", "css selector"}, {"value", css}});
        if (r.contains("error"))
            return std::nullopt;
        return r[kElementKey].get<std::string>();
    }
    std::vector<std::string> findAll(const std::string& css) {
        auto r = call("POST", path("/elements"), {{"using", "css selector"}, {"value", css}});
        std::vector<std::string> out;
        for (const auto& e : r)
            out.push_back(e[kElementKey].get<std::string>());
        return out;
    }
    std::string text(const std::string& element) {
        return call("GET", path("/element/" + element + "/text")).get<std::string>();
    }
    void click(const std::string& element) {
        call("POST", path("/element/" + element + "/click"), nlohmann::json::object());
    }
    /// Finds and clicks, again if the page redrew the element in between (stale reference).
    void clickCss(const std::string& css) {
        for (int attempt = 0;; ++attempt) {
            try {
                auto e = find(css);
                if (!e)
                    throw std::runtime_error("no element " + css);
                click(*e);
                return;
            } catch (const std::runtime_error& err) {
                if (attempt >= 4 ||
                    std::string(err.what()).find("stale element") == std::string::npos)
                    throw;
            }
        }
    }
    void type(const std::string& element, const std::string& text) {
        call("POST", path("/element/" + element + "/value"), {{"text", text}});
    }
    /// Runs `script` (a function body; arguments as `arguments[i]`) and returns its value.
    nlohmann::json execute(const std::string& script,
                           nlohmann::json args = nlohmann::json::array()) {
        return call("POST", path("/execute/sync"), {{"script", script}, {"args", std::move(args)}});
    }
    /// Moves the mouse to (dx, dy) from the element's centre.
    void hover(const std::string& element, int dx, int dy) {
        nlohmann::json move = {{"type", "pointerMove"},
                               {"duration", 0},
                               {"x", dx},
                               {"y", dy},
                               {"origin", {{kElementKey, element}}}};
        nlohmann::json pointer = {
            {"type", "pointer"}, {"id", "mouse"}, {"parameters", {{"pointerType", "mouse"}}}};
        pointer["actions"] = nlohmann::json::array({move});
        nlohmann::json body;
        body["actions"] = nlohmann::json::array({pointer});
        call("POST", path("/actions"), body);
    }
    void resize(int width, int height) {
        call("POST", path("/window/rect"), {{"width", width}, {"height", height}});
    }
    /// Saves a PNG of the viewport.
    void screenshot(const std::filesystem::path& file) {
        const auto png = base64Decode(call("GET", path("/screenshot")).get<std::string>());
        static constexpr unsigned char kSignature[8] = {0x89, 'P',  'N',  'G',
                                                        '\r', '\n', 0x1a, '\n'};
        if (png.size() < 8 || !std::equal(kSignature, kSignature + 8, png.begin()))
            throw std::runtime_error("WebDriver: the screenshot is not a PNG");
        std::filesystem::create_directories(file.parent_path());
        std::ofstream(file, std::ios::binary)
            .write(reinterpret_cast<const char*>(png.data()),
                   static_cast<std::streamsize>(png.size()));
    }

private:
    std::string path(const std::string& p) const { return "/session/" + session_ + p; }
    /// The reply's "value" (which holds "error" for a WebDriver error).
    nlohmann::json raw(const std::string& method, const std::string& p,
                       const nlohmann::json& body = {}) {
        httplib::Result r = method == "GET"    ? http_->Get(p)
                            : method == "POST" ? http_->Post(p, body.dump(), "application/json")
                                               : http_->Delete(p);
        if (!r)
            throw std::runtime_error("chromedriver: no reply to " + method + " " + p);
        auto j = nlohmann::json::parse(r->body, nullptr, false);
        if (j.is_discarded() || !j.contains("value"))
            throw std::runtime_error("chromedriver: bad reply " + r->body);
        return j["value"];
    }
    nlohmann::json call(const std::string& method, const std::string& p,
                        const nlohmann::json& body = {}) {
        auto v = raw(method, p, body);
        if (v.is_object() && v.contains("error"))
            throw std::runtime_error("WebDriver " + method + " " + p + ": " +
                                     v["error"].get<std::string>() + ": " +
                                     v.value("message", std::string()).substr(0, 300));
        return v;
    }

    pid_t pid_ = -1;
    int port_ = 0;
    std::unique_ptr<httplib::Client> http_;
    std::string session_;
};

} // namespace slicestation::webdriver
