#include "service/metrics_http.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <charconv>
#include <cstring>
#include <list>
#include <optional>
#include <vector>

#include <absl/strings/match.h>
#include <absl/strings/numbers.h>
#include <absl/strings/str_cat.h>
#include <absl/strings/str_split.h>
#include <spdlog/spdlog.h>

#include "service/prometheus_text.h"

namespace visq::service {
namespace {

using Clock = std::chrono::steady_clock;

// A request's head and body together stay under this; more is refused.
constexpr size_t kMaxRequestBytes = 8192;

struct HostPort {
  std::string host;
  int port = 0;
};

StatusOr<HostPort> ParseHostPort(const std::string& address) {
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0)
    return absl::InvalidArgumentError(absl::StrCat("--metrics-address '", address, "': expected HOST:PORT"));
  HostPort out;
  out.host = address.substr(0, colon);
  if (out.host.size() >= 2 && out.host.front() == '[' && out.host.back() == ']')
    out.host = out.host.substr(1, out.host.size() - 2);
  else if (out.host.find(':') != std::string::npos)
    return absl::InvalidArgumentError(
        absl::StrCat("--metrics-address '", address, "': write an IPv6 address in brackets, [::1]:PORT"));
  const std::string port = address.substr(colon + 1);
  const auto [end, error] = std::from_chars(port.data(), port.data() + port.size(), out.port);
  if (out.host.empty() || port.empty() || error != std::errc() || end != port.data() + port.size() ||
      out.port < 0 || out.port > 65535)
    return absl::InvalidArgumentError(absl::StrCat("--metrics-address '", address, "': expected HOST:PORT"));
  return out;
}

// A listening socket on the first of `where`'s addresses that binds;
// SO_REUSEADDR only, so a restart binds despite TIME_WAIT but a second
// server cannot share the port. -1 when none binds.
int Listen(const HostPort& where, int* port) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* found = nullptr;
  if (::getaddrinfo(where.host.c_str(), std::to_string(where.port).c_str(), &hints, &found) != 0) return -1;
  int fd = -1;
  for (const addrinfo* a = found; a != nullptr && fd < 0; a = a->ai_next) {
    fd = ::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol);
    if (fd < 0) continue;
    int yes = 1;
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
    if (::bind(fd, a->ai_addr, a->ai_addrlen) != 0 || ::listen(fd, 64) != 0) {
      ::close(fd);
      fd = -1;
    }
  }
  ::freeaddrinfo(found);
  if (fd < 0) return -1;
  sockaddr_storage bound{};
  socklen_t length = sizeof(bound);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&bound), &length);
  *port = bound.ss_family == AF_INET6 ? ntohs(reinterpret_cast<sockaddr_in6*>(&bound)->sin6_port)
                                      : ntohs(reinterpret_cast<sockaddr_in*>(&bound)->sin_port);
  return fd;
}

std::string HttpResponse(int status, const char* reason, const std::string& content_type, const std::string& body) {
  return absl::StrCat("HTTP/1.1 ", status, " ", reason, "\r\nContent-Type: ", content_type,
                      "\r\nContent-Length: ", body.size(), "\r\nConnection: close\r\n\r\n", body);
}

// One connection: its request as it arrives, then its answer as it leaves.
struct Connection {
  int fd = -1;
  Clock::time_point deadline;
  std::string in;
  std::string out;
  size_t sent = 0;
  bool answering = false;
};

// The answer to `in` once the whole request is there; nullopt while more
// is to come. Only GET /metrics is served; anything else is 404, with a body
// that names what is.
std::optional<std::string> Answer(const std::string& in, const std::function<ServerFigures()>& collect) {
  const size_t head_end = in.find("\r\n\r\n");
  if (head_end == std::string::npos) {
    if (in.size() >= kMaxRequestBytes) return HttpResponse(431, "Request Header Fields Too Large", "text/plain", "");
    return std::nullopt;
  }
  const std::vector<absl::string_view> lines = absl::StrSplit(absl::string_view(in).substr(0, head_end), "\r\n");
  uint64_t body_bytes = 0;
  for (size_t i = 1; i < lines.size(); ++i) {
    const size_t colon = lines[i].find(':');
    if (colon == absl::string_view::npos) continue;
    if (absl::EqualsIgnoreCase(lines[i].substr(0, colon), "content-length") &&
        !absl::SimpleAtoi(lines[i].substr(colon + 1), &body_bytes))
      return HttpResponse(400, "Bad Request", "text/plain", "");
  }
  // The body is read (not left unread, which would reset the connection
  // under the answer) and ignored.
  if (body_bytes > kMaxRequestBytes || head_end + 4 + body_bytes > kMaxRequestBytes)
    return HttpResponse(413, "Payload Too Large", "text/plain", "");
  if (in.size() < head_end + 4 + body_bytes) return std::nullopt;
  const std::vector<absl::string_view> request_line = absl::StrSplit(lines[0], ' ');
  if (request_line.size() == 3 && request_line[0] == "GET" &&
      (request_line[1] == "/metrics" || absl::StartsWith(request_line[1], "/metrics?")))
    return HttpResponse(200, "OK", kPrometheusContentType, RenderPrometheusText(collect()));
  return HttpResponse(404, "Not Found", "text/plain", "only GET /metrics is served here\n");
}

}  // namespace

Status ValidateMetricsAddress(const std::string& address) { return ParseHostPort(address).status(); }

StatusOr<std::unique_ptr<MetricsHttpServer>> MetricsHttpServer::Start(const std::string& address,
                                                                     std::function<ServerFigures()> collect,
                                                                     MetricsHttpLimits limits) {
  VISQ_ASSIGN_OR_RETURN(HostPort where, ParseHostPort(address));
  std::unique_ptr<MetricsHttpServer> server(new MetricsHttpServer());
  server->collect_ = std::move(collect);
  server->limits_ = limits;
  server->listen_fd_ = Listen(where, &server->port_);
  if (server->listen_fd_ < 0)
    return absl::UnavailableError(absl::StrCat("--metrics-address ", address,
                                               ": cannot listen there (address not local, or port in use)"));
  server->wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (server->wake_fd_ < 0) return absl::InternalError(absl::StrCat("eventfd: ", std::strerror(errno)));
  server->thread_ = std::thread([s = server.get()] { s->Serve(); });
  spdlog::info("metrics: GET http://{}:{}/metrics (at most {} connections, {} ms per request)",
               address.substr(0, address.rfind(':')), server->port_, limits.max_connections,
               limits.request_timeout.count());
  return server;
}

void MetricsHttpServer::Serve() {
  std::list<Connection> connections;
  std::vector<pollfd> polled;
  for (;;) {
    // What to wait for: the wake-up, new connections, each connection's
    // request or answer; until the nearest deadline.
    polled.clear();
    polled.push_back({wake_fd_, POLLIN, 0});
    polled.push_back({listen_fd_, POLLIN, 0});
    Clock::time_point nearest = Clock::now() + std::chrono::seconds(60);
    for (const Connection& c : connections) {
      polled.push_back({c.fd, static_cast<short>(c.answering ? POLLOUT : POLLIN), 0});
      nearest = std::min(nearest, c.deadline);
    }
    const auto wait = std::chrono::duration_cast<std::chrono::milliseconds>(nearest - Clock::now()).count();
    if (::poll(polled.data(), polled.size(), static_cast<int>(std::max<int64_t>(wait, 0) + 1)) < 0 && errno != EINTR) {
      spdlog::error("metrics: poll: {}", std::strerror(errno));
      break;
    }
    if (polled[0].revents != 0) break;  // Stop()

    // Each connection reads or writes what it can; one past its deadline,
    // done, or broken is closed.
    size_t i = 2;
    const auto now = Clock::now();
    for (auto it = connections.begin(); it != connections.end(); ++i) {
      Connection& c = *it;
      bool close = now >= c.deadline || (polled[i].revents & (POLLERR | POLLNVAL)) != 0;
      if (!close && !c.answering && (polled[i].revents & (POLLIN | POLLHUP)) != 0) {
        char buffer[4096];
        const ssize_t n = ::recv(c.fd, buffer, std::min(sizeof(buffer), kMaxRequestBytes + 1 - c.in.size()), 0);
        if (n > 0) {
          c.in.append(buffer, static_cast<size_t>(n));
          if (std::optional<std::string> answer = Answer(c.in, collect_)) {
            c.out = *std::move(answer);
            c.answering = true;
            c.deadline = now + limits_.request_timeout;
          }
        } else if (n == 0 || (errno != EAGAIN && errno != EINTR)) {
          close = true;
        }
      }
      if (!close && c.answering && (polled[i].revents & POLLOUT) != 0) {
        const ssize_t n = ::send(c.fd, c.out.data() + c.sent, c.out.size() - c.sent, MSG_NOSIGNAL);
        if (n > 0) c.sent += static_cast<size_t>(n);
        else if (errno != EAGAIN && errno != EINTR) close = true;
        if (c.sent == c.out.size()) {
          ::shutdown(c.fd, SHUT_WR);
          close = true;
        }
      }
      if (close) {
        ::close(c.fd);
        it = connections.erase(it);
      } else {
        ++it;
      }
    }

    // New connections, up to the cap; those beyond it are closed at once,
    // so they hold neither a descriptor nor the listen backlog.
    if ((polled[1].revents & POLLIN) != 0) {
      for (;;) {
        const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
        if (fd < 0) break;
        if (static_cast<int>(connections.size()) >= limits_.max_connections) {
          spdlog::debug("metrics: {} connections open, the limit (--metrics-max-connections): one refused",
                        connections.size());
          ::close(fd);
          continue;
        }
        connections.push_back({fd, Clock::now() + limits_.request_timeout, {}, {}, 0, false});
      }
    }
  }
  for (Connection& c : connections) ::close(c.fd);
}

void MetricsHttpServer::Stop() {
  if (!thread_.joinable()) return;
  const uint64_t one = 1;
  [[maybe_unused]] const ssize_t written = ::write(wake_fd_, &one, sizeof(one));
  thread_.join();
  ::close(listen_fd_);
  ::close(wake_fd_);
  listen_fd_ = wake_fd_ = -1;
}

MetricsHttpServer::~MetricsHttpServer() {
  Stop();
  if (listen_fd_ >= 0) ::close(listen_fd_);
  if (wake_fd_ >= 0) ::close(wake_fd_);
}

}  // namespace visq::service
