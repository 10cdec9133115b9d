// Connections that hold what other clients need: the real visq-server on
// loopback, its /metrics endpoint reached over raw sockets as a slow or
// greedy peer would.
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "server_process.h"
#include "test_support.h"

namespace visq {
namespace {

using testing::ScratchDir;
using testing::ServerProcess;

int ReadPort(const std::filesystem::path& file) {
  std::ifstream in(file);
  int port = 0;
  in >> port;
  return port;
}

// A TCP connection to 127.0.0.1:port; -1 when it cannot connect.
int ConnectTo(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = htons(static_cast<uint16_t>(port));
  if (fd < 0 || ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    if (fd >= 0) ::close(fd);
    return -1;
  }
  return fd;
}

void SetReceiveTimeout(int fd, std::chrono::milliseconds wait) {
  timeval timeout{static_cast<time_t>(wait.count() / 1000), static_cast<suseconds_t>(wait.count() % 1000 * 1000)};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
}

// Whether the server closed `fd` within `wait` (a read sees the end, or a
// reset).
bool ClosedWithin(int fd, std::chrono::milliseconds wait) {
  SetReceiveTimeout(fd, wait);
  char byte;
  const ssize_t n = ::recv(fd, &byte, 1, 0);
  return n == 0 || (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK);
}

// GET /metrics on a connection of its own; the whole answer (empty when
// none came within 10 s) and how long it took.
std::string Scrape(int port, double* ms) {
  const auto start = std::chrono::steady_clock::now();
  const int fd = ConnectTo(port);
  if (fd < 0) return {};
  SetReceiveTimeout(fd, std::chrono::seconds(10));
  const std::string request = "GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n";
  (void)::send(fd, request.data(), request.size(), MSG_NOSIGNAL);
  std::string answer;
  char buffer[4096];
  ssize_t n;
  while ((n = ::recv(fd, buffer, sizeof(buffer), 0)) > 0) answer.append(buffer, static_cast<size_t>(n));
  ::close(fd);
  *ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return answer;
}

// Slowloris: connections that send their request a byte every 300 ms. With
// a fixed pool of two threads and a read timeout that each byte renewed,
// two of them made /metrics answer no one; now they cannot delay another
// scrape, they are closed once --metrics-read-seconds has passed without a
// whole request, and connections beyond --metrics-max-connections are
// closed as they arrive.
TEST(HostileConnections, SlowAndSurplusMetricsConnectionsDoNotKeepAScraperWaiting) {
  ScratchDir repo, files;
  auto server = ServerProcess::Start({repo.path(),
                                      {"--metrics-address", "127.0.0.1:0", "--metrics-port-file",
                                       (files.path() / "mp").string(), "--metrics-read-seconds", "2",
                                       "--metrics-max-connections", "6"}});
  ASSERT_NE(server, nullptr);
  const int port = ReadPort(files.path() / "mp");
  ASSERT_GT(port, 0) << server->Log();

  // Four slow clients, each trickling its request.
  std::vector<int> slow;
  for (int i = 0; i < 4; ++i) {
    slow.push_back(ConnectTo(port));
    ASSERT_GE(slow.back(), 0);
  }
  const auto connected = std::chrono::steady_clock::now();
  std::atomic<bool> stop{false};
  std::thread trickle([&] {
    const std::string request = "GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n";
    for (size_t i = 0; i < request.size() && !stop; ++i) {
      for (int fd : slow) (void)::send(fd, &request[i], 1, MSG_NOSIGNAL);
      std::this_thread::sleep_for(std::chrono::milliseconds(300));
    }
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  double ms = 0;
  const std::string answer = Scrape(port, &ms);
  EXPECT_EQ(answer.rfind("HTTP/1.1 200", 0), 0u) << answer;
  EXPECT_NE(answer.find("visq_build_info"), std::string::npos);
  EXPECT_LT(ms, 1000) << "a scrape waited behind slow connections";

  // Two more fill the cap of six; a seventh is closed at once.
  const int fifth = ConnectTo(port), sixth = ConnectTo(port);
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const int seventh = ConnectTo(port);
  ASSERT_GE(seventh, 0);
  EXPECT_TRUE(ClosedWithin(seventh, std::chrono::milliseconds(1000))) << "a connection beyond the cap was kept";

  // The slow ones are closed once their 2 s are up, though still sending.
  for (int fd : slow) EXPECT_TRUE(ClosedWithin(fd, std::chrono::milliseconds(4000)));
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - connected).count(), 4.0);
  stop = true;
  trickle.join();
  for (int fd : slow) ::close(fd);
  for (int fd : {fifth, sixth, seventh})
    if (fd >= 0) ::close(fd);

  // Freed, the endpoint answers again.
  EXPECT_EQ(Scrape(port, &ms).rfind("HTTP/1.1 200", 0), 0u);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

}  // namespace
}  // namespace visq
