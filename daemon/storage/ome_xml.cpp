// OME-XML: the document written into a section image, and reading it back (pugixml).
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include "ome_text.hpp"

#include "slicestation/daemon/version.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <pugixml.hpp>

#include <array>
#include <bit>
#include <charconv>
#include <cmath>
#include <optional>
#include <random>
#include <vector>
namespace slicestation::daemon {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using core::makeError;
using ome_text::formatDouble;
using ome_text::quoted;

std::optional<double> parseDouble(std::string_view text) {
    while (!text.empty() && (text.front() == ' ' || text.front() == '+')) {
        text.remove_prefix(1);
    }
    double v = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (ec != std::errc() || end != text.data() + text.size() || !std::isfinite(v)) {
        return std::nullopt;
    }
    return v;
}

std::string xmlEscape(std::string_view text) {
    std::string out;
    out.reserve(text.size());
    for (const char c : text) {
        switch (c) {
        case '&':
            out += "&amp;";
            break;
        case '<':
            out += "&lt;";
            break;
        case '>':
            out += "&gt;";
            break;
        case '"':
            out += "&quot;";
            break;
        case '\'':
            out += "&apos;";
            break;
        default:
            out += c;
        }
    }
    return out;
}

std::string randomUuid() {
    std::random_device rd;
    std::array<std::uint8_t, 16> b{};
    for (auto& byte : b) {
        byte = static_cast<std::uint8_t>(rd());
    }
    b[6] = static_cast<std::uint8_t>((b[6] & 0x0f) | 0x40); // version 4 (RFC 4122 section 4.4)
    b[8] = static_cast<std::uint8_t>((b[8] & 0x3f) | 0x80);
    std::string out;
    constexpr std::string_view hex = "0123456789abcdef";
    for (std::size_t i = 0; i < b.size(); ++i) {
        if (i == 4 || i == 6 || i == 8 || i == 10) {
            out += '-';
        }
        out += hex[b[i] >> 4];
        out += hex[b[i] & 0xf];
    }
    return out;
}

// Reading back: pugixml parses, these look elements and attributes up by local name, so that
// another writer's namespace prefix (<ome:Pixels>) reads like ours.

std::string_view localName(std::string_view name) {
    const auto colon = name.find(':');
    return colon == std::string_view::npos ? name : name.substr(colon + 1);
}

pugi::xml_node child(pugi::xml_node parent, std::string_view name) {
    for (pugi::xml_node c = parent.first_child(); c; c = c.next_sibling())
        if (c.type() == pugi::node_element && localName(c.name()) == name)
            return c;
    return {};
}

/// The attribute's value, or nullptr when it has none.
const char* attribute(pugi::xml_node e, std::string_view name) {
    for (pugi::xml_attribute a = e.first_attribute(); a; a = a.next_attribute())
        if (localName(a.name()) == name)
            return a.value();
    return nullptr;
}

/// The document, or IoError naming pugixml's complaint and its byte offset. One root element
/// only, and nothing but comments, processing instructions and DOCTYPE beside it.
core::Result<pugi::xml_node> loadDocument(pugi::xml_document& doc, std::string_view xml) {
    const pugi::xml_parse_result r =
        doc.load_buffer(xml.data(), xml.size(), pugi::parse_default, pugi::encoding_utf8);
    if (!r)
        return makeError(ErrorCode::IoError, "malformed OME-XML at byte " +
                                                 std::to_string(r.offset) + ": " + r.description());
    pugi::xml_node root;
    for (pugi::xml_node n = doc.first_child(); n; n = n.next_sibling()) {
        if (n.type() == pugi::node_element && !root)
            root = n;
        else if (n.type() == pugi::node_element || n.type() == pugi::node_pcdata ||
                 n.type() == pugi::node_cdata)
            return makeError(ErrorCode::IoError,
                             "malformed OME-XML: content after the root element");
    }
    if (!root)
        return makeError(ErrorCode::IoError, "malformed OME-XML: no root element");
    return root;
}

/// Factor to µm of an OME UnitsLength symbol; "reference frame" (the schema's default for stage
/// positions) is taken as µm, the stage's own unit.
std::optional<double> lengthToUm(std::string_view unit) {
    if (unit.empty() || unit == "µm" || unit == "\xce\xbcm" || unit == "um" ||
        unit == "reference frame") {
        return 1.0;
    }
    if (unit == "nm")
        return 1e-3;
    if (unit == "pm")
        return 1e-6;
    if (unit == "Å")
        return 1e-4;
    if (unit == "mm")
        return 1e3;
    if (unit == "cm")
        return 1e4;
    if (unit == "m")
        return 1e6;
    return std::nullopt;
}

/// Factor to µs of an OME UnitsTime symbol (default: s).
std::optional<double> timeToUs(std::string_view unit) {
    if (unit.empty() || unit == "s")
        return 1e6;
    if (unit == "ms")
        return 1e3;
    if (unit == "µs" || unit == "\xce\xbcs" || unit == "us")
        return 1.0;
    if (unit == "ns")
        return 1e-3;
    if (unit == "min")
        return 6e7;
    if (unit == "h")
        return 3.6e9;
    return std::nullopt;
}

/// The magnification an objective's name states ("4x", "10X", "20x/0.75"), if it states one.
std::optional<double> magnificationOf(std::string_view objective) {
    const auto x = objective.find_first_of("xX");
    if (x == std::string_view::npos || x == 0)
        return std::nullopt;
    const auto v = parseDouble(objective.substr(0, x));
    return v && *v > 0 ? v : std::nullopt;
}

/// OME's Color: the RGBA bytes as one signed 32-bit integer (xsd:int; -1 is opaque white).
std::string omeColor(std::uint32_t rgba) {
    return std::to_string(static_cast<std::int32_t>(rgba));
}

/// A Channel@Color back to 0xRRGGBBAA; IoError unless it is a 32-bit integer.
core::Result<std::uint32_t> parseColor(const char* text) {
    const auto v = parseDouble(text);
    if (!v || !(*v >= -2147483648.0 && *v <= 2147483647.0 && *v == std::floor(*v)))
        return makeError(ErrorCode::IoError,
                         "OME-XML: Color=\"" + std::string(text) + "\" is not a 32-bit integer");
    return static_cast<std::uint32_t>(static_cast<std::int32_t>(*v));
}

/// The first Channel's name, colour and gain into `info` (none: defaults kept).
core::Result<void> readChannel(pugi::xml_node channel, OmeTiffInfo& info) {
    if (!channel)
        return {};
    if (const char* n = attribute(channel, "Name"))
        info.channel = n;
    if (const char* color = attribute(channel, "Color")) {
        auto rgba = parseColor(color);
        if (!rgba)
            return rgba.error();
        info.channelRgba = *rgba;
    }
    const pugi::xml_node ds = child(channel, "DetectorSettings");
    if (const char* gain = ds ? attribute(ds, "Gain") : nullptr) {
        const auto v = parseDouble(gain);
        if (!v)
            return makeError(ErrorCode::IoError,
                             "OME-XML: Gain=\"" + std::string(gain) + "\" is not a number");
        info.gain = *v;
    }
    return {};
}

const char* pixelType(int cvType) {
    return CV_MAT_DEPTH(cvType) == CV_16U ? "uint16" : "uint8";
}

} // namespace

std::string makeOmeXml(int width, int height, int cvType, const OmeTiffInfo& info) {
    const bool rgb = CV_MAT_CN(cvType) == 3;
    const std::string um = "µm";
    std::string x;
    x += "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n";
    x += "<OME xmlns=\"http://www.openmicroscopy.org/Schemas/OME/2016-06\" "
         "xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" "
         "xsi:schemaLocation=\"http://www.openmicroscopy.org/Schemas/OME/2016-06 "
         "http://www.openmicroscopy.org/Schemas/OME/2016-06/ome.xsd\" "
         "Creator=\"slicestation " +
         std::string(kVersion) + "\" UUID=\"urn:uuid:" + randomUuid() + "\">\n";
    // Element order follows the schema's sequences: Instrument before Image; in Instrument,
    // Detector before Objective; in Image, AcquisitionDate, InstrumentRef, ObjectiveSettings,
    // StageLabel, Pixels; in Pixels, Channel, TiffData, Plane.
    x += "  <Instrument ID=\"Instrument:0\">\n";
    x += "    <Detector ID=\"Detector:0:0\" Type=\"CMOS\"/>\n";
    if (!info.objective.empty()) {
        x += "    <Objective ID=\"Objective:0:0\" Model=\"" + xmlEscape(info.objective) + "\"";
        if (const auto m = magnificationOf(info.objective))
            x += " NominalMagnification=\"" + formatDouble(*m) + "\"";
        x += "/>\n";
    }
    x += "  </Instrument>\n";
    x += "  <Image ID=\"Image:0\" Name=\"" + xmlEscape(info.name) + "\">\n";
    if (!info.acquiredUtc.empty()) {
        x += "    <AcquisitionDate>" + xmlEscape(info.acquiredUtc) + "</AcquisitionDate>\n";
    }
    x += "    <InstrumentRef ID=\"Instrument:0\"/>\n";
    if (!info.objective.empty())
        x += "    <ObjectiveSettings ID=\"Objective:0:0\"/>\n";
    x += "    <StageLabel Name=\"image centre\" X=\"" + formatDouble(info.stage.xUm) +
         "\" XUnit=\"" + um + "\" Y=\"" + formatDouble(info.stage.yUm) + "\" YUnit=\"" + um +
         "\" Z=\"" + formatDouble(info.stage.zUm) + "\" ZUnit=\"" + um + "\"/>\n";
    x += "    <Pixels ID=\"Pixels:0\" DimensionOrder=\"XYCZT\" Type=\"" +
         std::string(pixelType(cvType)) + "\" SignificantBits=\"" +
         std::to_string(CV_MAT_DEPTH(cvType) == CV_16U ? 16 : 8) + "\" BigEndian=\"" +
         (std::endian::native == std::endian::big ? "true" : "false") + "\" Interleaved=\"" +
         (rgb ? "true" : "false") + "\" SizeX=\"" + std::to_string(width) + "\" SizeY=\"" +
         std::to_string(height) + "\" SizeZ=\"1\" SizeC=\"" + (rgb ? "3" : "1") +
         "\" SizeT=\"1\" PhysicalSizeX=\"" + formatDouble(info.umPerPx) +
         "\" PhysicalSizeXUnit=\"" + um + "\" PhysicalSizeY=\"" + formatDouble(info.umPerPx) +
         "\" PhysicalSizeYUnit=\"" + um + "\">\n";
    x += "      <Channel ID=\"Channel:0:0\" Name=\"" + xmlEscape(info.channel) +
         "\" SamplesPerPixel=\"" + (rgb ? "3" : "1") + "\" Color=\"" + omeColor(info.channelRgba) +
         "\">\n";
    x += "        <DetectorSettings ID=\"Detector:0:0\" Gain=\"" + formatDouble(info.gain) +
         "\"/>\n";
    x += "      </Channel>\n";
    x += "      <TiffData IFD=\"0\" PlaneCount=\"1\"/>\n";
    x += "      <Plane TheZ=\"0\" TheC=\"0\" TheT=\"0\" ExposureTime=\"" +
         std::to_string(info.exposureUs) + "\" ExposureTimeUnit=\"µs\" PositionX=\"" +
         formatDouble(info.stage.xUm) + "\" PositionXUnit=\"" + um + "\" PositionY=\"" +
         formatDouble(info.stage.yUm) + "\" PositionYUnit=\"" + um + "\" PositionZ=\"" +
         formatDouble(info.stage.zUm) + "\" PositionZUnit=\"" + um + "\"/>\n";
    x += "    </Pixels>\n";
    x += "  </Image>\n";
    x += "</OME>\n";
    return x;
}

core::Result<OmeXmlContent> parseOmeXml(std::string_view xml) {
    pugi::xml_document document;
    auto doc = loadDocument(document, xml);
    if (!doc)
        return doc.error();
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::IoError, "OME-XML: " + what);
    };
    if (localName(doc->name()) != "OME")
        return bad("root element is <" + std::string(localName(doc->name())) + ">, not <OME>");
    const pugi::xml_node image = child(*doc, "Image");
    if (!image)
        return bad("no <Image>");
    const pugi::xml_node pixels = child(image, "Pixels");
    if (!pixels)
        return bad("no <Pixels> in the first <Image>");

    OmeXmlContent out;
    auto& info = out.info;
    if (const char* n = attribute(image, "Name"))
        info.name = n;
    if (const pugi::xml_node d = child(image, "AcquisitionDate"))
        info.acquiredUtc = d.child_value();

    const auto number = [&](pugi::xml_node e, std::string_view key) -> core::Result<double> {
        const char* text = attribute(e, key);
        if (text == nullptr)
            return bad("no " + std::string(key) + " in <" + std::string(localName(e.name())) + ">");
        const auto v = parseDouble(text);
        if (!v)
            return bad(std::string(key) + "=\"" + text + "\" is not a number");
        return *v;
    };
    const auto length = [&](pugi::xml_node e, std::string_view key) -> core::Result<double> {
        auto v = number(e, key);
        if (!v)
            return v;
        const char* unit = attribute(e, std::string(key) + "Unit");
        const auto factor = lengthToUm(unit ? unit : std::string_view());
        if (!factor)
            return bad(std::string(key) + "Unit=\"" + unit + "\" is not a known length");
        return *v * *factor;
    };

    for (const char* key : {"SizeX", "SizeY"}) {
        auto v = number(pixels, key);
        if (!v)
            return v.error();
        // A pixel count: a whole number that an int holds (found by fuzz_small_formats:
        // SizeX="1.6e55" was cast to int, which is undefined).
        if (!(*v >= 1 && *v <= 2147483647.0 && *v == std::floor(*v)))
            return bad(std::string(key) + "=\"" + attribute(pixels, key) +
                       "\" is not a pixel count");
        (std::string_view(key) == "SizeX" ? out.sizeX : out.sizeY) = static_cast<int>(*v);
    }
    auto sizeUm = length(pixels, "PhysicalSizeX");
    if (!sizeUm)
        return sizeUm.error();
    if (!(*sizeUm > 0))
        return bad("PhysicalSizeX must be > 0");
    info.umPerPx = *sizeUm;

    if (const pugi::xml_node objective = child(child(*doc, "Instrument"), "Objective"))
        if (const char* model = attribute(objective, "Model"))
            info.objective = model;
    if (auto channel = readChannel(child(pixels, "Channel"), info); !channel)
        return channel.error();
    if (const pugi::xml_node plane = child(pixels, "Plane")) {
        double* targets[] = {&info.stage.xUm, &info.stage.yUm, &info.stage.zUm};
        const char* keys[] = {"PositionX", "PositionY", "PositionZ"};
        for (int i = 0; i < 3; ++i) {
            if (attribute(plane, keys[i]) == nullptr)
                continue;
            auto v = length(plane, keys[i]);
            if (!v)
                return v.error();
            *targets[i] = *v;
        }
        if (attribute(plane, "ExposureTime") != nullptr) {
            auto v = number(plane, "ExposureTime");
            if (!v)
                return v.error();
            const char* unit = attribute(plane, "ExposureTimeUnit");
            const auto factor = timeToUs(unit ? unit : std::string_view());
            if (!factor)
                return bad("ExposureTimeUnit=\"" + std::string(unit) + "\" is not a known time");
            info.exposureUs = std::llround(*v * *factor);
        }
    }
    return out;
}

} // namespace slicestation::daemon
