// visq light-visibility: exact visibility of an area light from points or a
// receiver patch, over LightVisibilityStream in batches, so that any size
// fits the server's message limit and neither side holds every point's
// request at once.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <optional>

#include <fmt/format.h>
#include <glm/glm.hpp>

#include "cli_common.h"

namespace visq::cli {
namespace {

// Points per stream message: about 70 bytes each on the wire, far below the
// server's 16 MiB message limit and its 1,000,000 points per message.
constexpr size_t kBatchPoints = 65536;
// The most points one command asks about: a 4096 x 4096 receiver, the
// image RPCs' own limit; the answers alone are then 200 MiB of doubles.
constexpr uint64_t kMaxPoints = uint64_t{4096} * 4096;

struct LightOptions {
  std::string scene, light, points_file, receiver, png, npy, exr;
  double radiance = 1.0;
  std::optional<double> shadow_tolerance;
  uint32_t width = 64, height = 64;
  bool polygons = false;
};

struct Point {
  glm::dvec3 position;
  bool has_normal = false;
  glm::dvec3 normal{0.0};
};

glm::dvec3 ToGlm(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

StatusOr<std::vector<Point>> ReadPoints(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(fmt::format("--points: cannot read {}", path));
  std::vector<Point> points;
  std::string line;
  for (size_t number = 1; std::getline(in, line); ++number) {
    const size_t first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#') continue;
    double v[6];
    char tail;
    const int n = std::sscanf(line.c_str(), "%lf %lf %lf %lf %lf %lf %c", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5],
                              &tail);
    if (n != 3 && n != 6)
      return absl::InvalidArgumentError(
          fmt::format("--points: {} line {}: expected 'x y z' or 'x y z nx ny nz', got '{}'", path, number, line));
    for (int i = 0; i < n; ++i)
      if (!std::isfinite(v[i]))
        return absl::InvalidArgumentError(fmt::format("--points: {} line {}: not a finite number", path, number));
    if (points.size() == kMaxPoints)
      return absl::ResourceExhaustedError(fmt::format("--points: more than {} points in {}", kMaxPoints, path));
    points.push_back({{v[0], v[1], v[2]}, n == 6, {n == 6 ? v[3] : 0, n == 6 ? v[4] : 0, n == 6 ? v[5] : 0}});
  }
  if (points.empty()) return absl::InvalidArgumentError(fmt::format("--points: {} holds no point", path));
  return points;
}

// The polygon's front normal (counter-clockwise: Newell's method) and centre.
void LightFrame(const v1::Polygon& light, glm::dvec3* normal, glm::dvec3* centre) {
  *normal = glm::dvec3(0.0);
  *centre = glm::dvec3(0.0);
  const int n = light.vertices_size();
  for (int i = 0; i < n; ++i) {
    const glm::dvec3 a = ToGlm(light.vertices(i)), b = ToGlm(light.vertices((i + 1) % n));
    *normal += glm::dvec3((a.y - b.y) * (a.z + b.z), (a.z - b.z) * (a.x + b.x), (a.x - b.x) * (a.y + b.y));
    *centre += a / double(n);
  }
}

Status RunLightVisibility(const LightOptions& o, Cli& cli) {
  v1::LightVisibilityRequest first;
  first.mutable_scene()->set_name(o.scene);
  first.set_radiance(o.radiance);
  first.set_want_polygons(o.polygons);
  if (o.shadow_tolerance) first.set_shadow_tolerance(*o.shadow_tolerance);
  for (size_t start = 0; start <= o.light.size();) {
    size_t end = o.light.find(';', start);
    if (end == std::string::npos) end = o.light.size();
    if (!ParseVec3(o.light.substr(start, end - start), first.mutable_light()->add_vertices()))
      return absl::InvalidArgumentError("--light: expected 'x,y,z;x,y,z;...'");
    start = end + 1;
  }
  const bool grid = !o.receiver.empty();
  if (grid == !o.points_file.empty())
    return absl::InvalidArgumentError("--points, --receiver: give one of them");
  if (!grid && (!o.png.empty() || !o.npy.empty() || !o.exr.empty()))
    return absl::InvalidArgumentError("--png, --npy, --exr: need --receiver (points from a file have no image layout)");

  // The points: a file's, or the receiver's texel centres (row y along
  // edge_v), made one at a time.
  std::vector<Point> file_points;
  glm::dvec3 origin(0.0), edge_u(0.0), edge_v(0.0), receiver_normal(0.0);
  uint64_t total = 0;
  if (grid) {
    v1::Patch patch;
    if (!ParsePatch(o.receiver, &patch))
      return absl::InvalidArgumentError("--receiver: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz'");
    if (o.width < 1 || o.width > 4096 || o.height < 1 || o.height > 4096)
      return absl::InvalidArgumentError(
          fmt::format("--width, --height: {} x {}; each must be in 1..4096", o.width, o.height));
    origin = ToGlm(patch.origin());
    edge_u = ToGlm(patch.edge_u());
    edge_v = ToGlm(patch.edge_v());
    const glm::dvec3 n = glm::cross(edge_u, edge_v);
    if (!(glm::length(n) > 0)) return absl::InvalidArgumentError("--receiver: edge_u and edge_v are parallel");
    receiver_normal = glm::normalize(n);
    total = uint64_t{o.width} * o.height;
  } else {
    VISQ_ASSIGN_OR_RETURN(file_points, ReadPoints(o.points_file));
    total = file_points.size();
  }
  auto point_at = [&](uint64_t i) -> Point {
    if (!grid) return file_points[i];
    const uint64_t x = i % o.width, y = i / o.width;
    return {origin + edge_u * ((x + 0.5) / o.width) + edge_v * ((y + 0.5) / o.height), true, receiver_normal};
  };

  // A light whose front faces away from every point lights none of them:
  // most likely its vertices are in clockwise order.
  if (first.light().vertices_size() >= 3) {
    glm::dvec3 light_normal, centre;
    LightFrame(first.light(), &light_normal, &centre);
    bool any_in_front = false;
    for (uint64_t i = 0; i < total && !any_in_front; ++i)
      any_in_front = glm::dot(point_at(i).position - centre, light_normal) > 0;
    if (!any_in_front && glm::length(light_normal) > 0) {
      const glm::dvec3 n = glm::normalize(light_normal);
      fmt::print(stderr,
                 "visq: warning: the light's front (counter-clockwise, towards ({:.3g}, {:.3g}, {:.3g})) faces away "
                 "from every point; every answer is 0 (reverse --light's vertices to turn it round)\n",
                 n.x, n.y, n.z);
    }
  }

  // Answers in point order; the per-point text lines are printed as they come.
  std::vector<float> fraction;
  if (grid) fraction.reserve(total);
  v1::LightVisibilityResponse merged;  // --json: every point, the last batch's tree and cache
  uint64_t sent = 0, answered = 0, batches = 0;
  v1::LightTreeStats tree_sums;
  // The answers of the stream's batches are its progress (one batch says
  // nothing until it is answered: until then, the time worked).
  std::optional<Waiting> waiting;
  waiting.emplace(cli.flags, "light-visibility");
  auto next = [&](v1::LightVisibilityRequest* batch) {
    if (sent == total) return false;
    *batch->mutable_scene() = first.scene();
    *batch->mutable_light() = first.light();
    batch->set_radiance(first.radiance());
    batch->set_want_polygons(first.want_polygons());
    if (first.has_shadow_tolerance()) batch->set_shadow_tolerance(first.shadow_tolerance());
    const uint64_t end = std::min<uint64_t>(total, sent + kBatchPoints);
    for (; sent < end; ++sent) {
      const Point p = point_at(sent);
      auto* point = batch->add_points();
      point->mutable_position()->set_x(p.position.x);
      point->mutable_position()->set_y(p.position.y);
      point->mutable_position()->set_z(p.position.z);
      if (p.has_normal) {
        point->mutable_normal()->set_x(p.normal.x);
        point->mutable_normal()->set_y(p.normal.y);
        point->mutable_normal()->set_z(p.normal.z);
      }
    }
    return true;
  };
  auto answer = [&](v1::LightVisibilityResponse& response) -> Status {
    ++batches;
    answered += response.points_size();
    const auto& t = response.tree();
    tree_sums.set_trees(std::max(tree_sums.trees(), t.trees()));
    tree_sums.set_trees_created(tree_sums.trees_created() + t.trees_created());
    tree_sums.set_queries(tree_sums.queries() + t.queries());
    tree_sums.set_wholly_visible(tree_sums.wholly_visible() + t.wholly_visible());
    tree_sums.set_wholly_hidden(tree_sums.wholly_hidden() + t.wholly_hidden());
    tree_sums.set_subtracted_directly(tree_sums.subtracted_directly() + t.subtracted_directly());
    // Sizes are the cached trees' after this batch.
    tree_sums.set_nodes(t.nodes());
    tree_sums.set_refinements(t.refinements());
    tree_sums.set_memory_bytes(t.memory_bytes());
    for (const auto& p : response.points()) {
      if (grid) fraction.push_back(static_cast<float>(p.visible_fraction()));
      else if (!cli.flags.json) fmt::print("{:.9f} {:.9g}\n", p.visible_fraction(), p.irradiance());
    }
    if (cli.flags.json) {
      for (auto& p : *response.mutable_points()) *merged.add_points() = std::move(p);
      *merged.mutable_tree() = response.tree();
      *merged.mutable_cache() = response.cache();
      *merged.mutable_accuracy() = response.accuracy();
      *merged.mutable_timing() = response.timing();
    }
    waiting->Progress(answered, total, "points");
    return absl::OkStatus();
  };
  auto client = MakeClient(cli.flags);
  const auto start = std::chrono::steady_clock::now();
  const Status streamed = client.LightVisibilityStream(o.scene, next, answer);
  waiting.reset();  // its last line before the answer's
  const double total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  VISQ_RETURN_IF_ERROR(streamed);
  if (answered != total)
    return absl::DataLossError(fmt::format("{} answers for {} points", answered, total));

  if (!o.png.empty()) VISQ_RETURN_IF_ERROR(WritePng(o.png, o.width, o.height, 1, fraction));
  if (!o.npy.empty()) VISQ_RETURN_IF_ERROR(WriteNpy(o.npy, {o.height, o.width}, fraction));
  if (!o.exr.empty()) VISQ_RETURN_IF_ERROR(WriteExr(o.exr, o.width, o.height, 1, fraction));
  if (cli.flags.json) {
    // Several batches: the whole stream's time as this client saw it.
    if (batches > 1) {
      merged.clear_timing();
      merged.mutable_timing()->set_total_ms(total_ms);
    }
    fmt::print("{}", ToJson(merged));
    return absl::OkStatus();
  }
  const auto& t = tree_sums;
  fmt::print("{} points in {} batch(es), exact; {} tree(s), {} built ({} nodes, {} refinements, {} bytes; {} of their "
             "{} queries answered before them: {} wholly visible, {} wholly hidden, {} subtracted directly); {:.1f} ms\n",
             answered, batches, t.trees(), t.trees_created(), t.nodes(), t.refinements(), t.memory_bytes(),
             t.wholly_visible() + t.wholly_hidden() + t.subtracted_directly(), t.queries(), t.wholly_visible(),
             t.wholly_hidden(), t.subtracted_directly(), total_ms);
  PrintWritten(o.png, o.npy, o.exr);
  return absl::OkStatus();
}

}  // namespace

void AddLightCommands(Cli& cli) {
  auto lv = std::make_shared<LightOptions>();
  auto* command =
      cli.app.add_subcommand("light-visibility", "Exact visibility of an area light from points (or a receiver patch)");
  command->add_option("--scene", lv->scene, "Scene name")->required();
  command->add_option("--light", lv->light, "Light polygon 'x,y,z;x,y,z;...' (front: counter-clockwise)")->required();
  command->add_option("--radiance", lv->radiance, "Emitted radiance")->capture_default_str();
  command->add_option("--shadow-tolerance", lv->shadow_tolerance,
                      "Per point, leave out occluders with small shadows while their areas sum to at most this "
                      "share of the light, stated as the point's error (0: every answer exact; default: the "
                      "server's)")
      ->check(CLI::Range(0.0, 1.0));
  command->add_option("--points", lv->points_file,
                      "File of points, one 'x y z [nx ny nz]' per line ('#' comments); prints 'fraction irradiance' "
                      "per point");
  command->add_option("--receiver", lv->receiver, "Or: a receiver patch sampled at texel centers");
  command->add_option("--width", lv->width, "Receiver texels across (1..4096)")->capture_default_str();
  command->add_option("--height", lv->height, "Receiver texels down (1..4096)")->capture_default_str();
  command->add_option("--png", lv->png, "Write the receiver's exact soft shadow (visible fraction) as a PNG");
  command->add_option("--npy", lv->npy, "Write the receiver's visible fractions as a float32 .npy (height, width)");
  command->add_option("--exr", lv->exr, "Write the receiver's visible fractions as a float OpenEXR image (as the PNG)");
  command->add_flag("--polygons", lv->polygons, "Return the visible parts of the light (with --json)");
  OnRun(command, cli, lv, RunLightVisibility);
}

}  // namespace visq::cli
