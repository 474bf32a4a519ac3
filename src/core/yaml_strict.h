// Strict YAML parsing (issue 16), defined in core/config.cpp beside the config
// composer that is its main user; kept out of config.h, which every file includes.
#pragma once
#include <string>

namespace YAML {
class Node;
}

namespace mc {

// Strict YAML for every file a user writes (configs, constraint specs, skeletons):
// yaml-cpp's own parse, then refused with a UserError naming `name` and the line:
// a second document, a key that is a list or mapping, a key given twice (yaml-cpp
// would silently keep the first), nesting deeper than 64 levels or aliases that
// expand past a million nodes (which would recurse or hang). `what` words the
// message, e.g. "malformed YAML".
YAML::Node parse_yaml_strict(const std::string& text, const std::string& name, const std::string& what = "YAML");
// The same for a file: UserError when it is missing, a directory or unreadable.
YAML::Node load_yaml_file_strict(const std::string& path, const std::string& what = "YAML");

}  // namespace mc
