#pragma once
// Scene loading entry points. Every error is an InputError with one line naming the file.
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "engine/scene/scene.h"

namespace bl {

// Loads a backlight JSON scene, a .gltf/.glb file rendered directly, or a Mitsuba 3 .xml scene.
// Returns a prepared scene.
std::unique_ptr<Scene> load_scene(const std::string& path);
std::unique_ptr<Scene> load_json_scene(const std::string& path);
std::unique_ptr<Scene> load_gltf_scene(const std::string& path);
std::unique_ptr<Scene> load_xml_scene(const std::string& path);
// A scene from a parsed JSON document; relative file names resolve against `path`'s folder and
// errors name `path` (the XML loader builds its scene this way).
std::unique_ptr<Scene> build_json_scene(const nlohmann::json& root, const std::string& path);

// Under MPI, requires every rank to have loaded the same content (Scene::content_hash; the
// command line and the files it names are compared at start-up, not the textures, meshes and
// grids a scene refers to): one agreed line, exit 2, where they differ. A collective operation:
// call it on every rank at the same point. Nothing on one process.
void require_same_scene(const Scene& scene);

// Triangle meshes of every primitive of a glTF file's default scene, node transforms applied,
// then `to_world`. Used by the `gltf` shape type, which takes its material from the JSON scene:
// the file's materials and vertex colours (COLOR_0, part of a glTF material's base colour) are
// not read.
std::vector<Mesh> load_gltf_meshes(const std::string& path, const Transform& to_world);
// The same, handing its warnings (point and line primitives it skipped) to the caller, which
// prints them once its own load has succeeded: a scene that fails to load gets its one error line.
std::vector<Mesh> load_gltf_meshes(const std::string& path, const Transform& to_world,
                                   std::vector<std::string>& warnings);

// Finishes a mesh built in object space: transforms to world, fixes winding for mirroring
// transforms, optionally flips normals, pads positions for Embree and checks it.
void finalize_mesh(Mesh& mesh, const Transform& to_world, bool flip_normals, const std::string& where);

// Builds the built-in shapes in object space.
Mesh make_rectangle();
Mesh make_cube();

// Applies `--set NAME=FILE|v1,v2,...`; errors name the parameter and the problem.
void apply_override(Scene& scene, const std::string& assignment);
// Sets parameter `name` to `values` (one value for every element, or three for every pixel of an
// RGB image, broadcast), checked as --set checks them; `where` starts the errors ("--set", "set").
void set_param_values(Scene& scene, const std::string& name, std::vector<float> values, const std::string& where);
// Checks a parameter's values: finite and inside [lower, upper].
void validate_param(const Param& p, const std::string& where);

}  // namespace bl
