// End-to-end latency through gRPC against a running visq-server: a warm
// single-point LightVisibility (the exact light's tree cached) and a
// PatchVisibility of 32 x 32 by 32 x 32 samples (1M rays), both on a scene
// the server holds. Prints percentiles; not a test.
//
//   visq_bench_rpc_latency --server 127.0.0.1:50051 --scene sponza
//     --light "x,y,z;x,y,z;..." --point "x,y,z" --normal "x,y,z"
//     --source "o;u;v" --receiver "o;u;v" [--repeats 200]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "latency_figures.h"
#include "visq_client.h"

namespace {

using visq::bench::Report;

bool ParseVec3(const std::string& text, visq::v1::Vec3* out) {
  double x, y, z;
  if (std::sscanf(text.c_str(), "%lf,%lf,%lf", &x, &y, &z) != 3) return false;
  out->set_x(x);
  out->set_y(y);
  out->set_z(z);
  return true;
}

bool ParsePatch(const std::string& text, visq::v1::Patch* out) {
  const size_t a = text.find(';'), b = text.find(';', a + 1);
  return a != std::string::npos && b != std::string::npos && ParseVec3(text.substr(0, a), out->mutable_origin()) &&
         ParseVec3(text.substr(a + 1, b - a - 1), out->mutable_edge_u()) &&
         ParseVec3(text.substr(b + 1), out->mutable_edge_v());
}

template <typename Call>
std::vector<double> Time(int repeats, Call call) {
  std::vector<double> ms;
  for (int i = 0; i < repeats; ++i) {
    const auto start = std::chrono::steady_clock::now();
    if (!call()) break;
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
  }
  return ms;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"visq RPC latency benchmark"};
  std::string server = "127.0.0.1:50051", scene, light, point, normal = "0,1,0", source, receiver;
  int repeats = 200;
  app.add_option("--server", server)->capture_default_str();
  app.add_option("--scene", scene)->required();
  app.add_option("--light", light, "Light polygon 'x,y,z;...'");
  app.add_option("--point", point, "Receiver point 'x,y,z'");
  app.add_option("--normal", normal)->capture_default_str();
  app.add_option("--source", source, "PatchVisibility source patch 'o;u;v'");
  app.add_option("--receiver", receiver, "PatchVisibility receiver patch 'o;u;v'");
  app.add_option("--repeats", repeats)->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  visq::client::Client client({.address = server});

  if (!light.empty() && !point.empty()) {
    visq::v1::LightVisibilityRequest request;
    request.mutable_scene()->set_name(scene);
    for (size_t start = 0; start < light.size();) {
      size_t end = light.find(';', start);
      if (end == std::string::npos) end = light.size();
      ParseVec3(light.substr(start, end - start), request.mutable_light()->add_vertices());
      start = end + 1;
    }
    auto* p = request.add_points();
    ParseVec3(point, p->mutable_position());
    ParseVec3(normal, p->mutable_normal());
    auto warm = client.LightVisibility(request);  // builds (or finds) the light's tree
    if (!warm.ok()) {
      std::fprintf(stderr, "LightVisibility: %s\n", std::string(warm.status().message()).c_str());
      return 1;
    }
    std::printf("light visibility of the point: %.6f (tree %s, %llu nodes)\n", warm->points(0).visible_fraction(),
                warm->tree().reused() ? "reused" : "built", static_cast<unsigned long long>(warm->tree().nodes()));
    Report("LightVisibility, 1 point, warm tree", Time(repeats, [&] { return client.LightVisibility(request).ok(); }));
  }
  if (!source.empty() && !receiver.empty()) {
    visq::v1::PatchVisibilityRequest request;
    request.mutable_scene()->set_name(scene);
    ParsePatch(source, request.mutable_source());
    ParsePatch(receiver, request.mutable_receiver());
    for (auto method : {visq::v1::RASTER, visq::v1::RAYCAST}) {
      request.set_method(method);
      auto first = client.PatchVisibility(request);
      if (!first.ok()) {
        std::fprintf(stderr, "PatchVisibility: %s\n", std::string(first.status().message()).c_str());
        return 1;
      }
      std::printf("%s mutual visible fraction %.5f\n", method == visq::v1::RASTER ? "RASTER" : "RAYCAST",
                  first->mutual_visible_fraction());
      Report(method == visq::v1::RASTER ? "PatchVisibility 32^2 x 32^2, RASTER" : "PatchVisibility 32^2 x 32^2, RAYCAST",
             Time(std::max(1, repeats / 20), [&] { return client.PatchVisibility(request).ok(); }));
    }
  }
  return 0;
}
