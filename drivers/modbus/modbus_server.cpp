// Modbus TCP server of the PLC link: libmodbus for listen and reply, our own framing, screening and poll loop.
#include "drivers/modbus/modbus_server.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <system_error>
#include <thread>
#include <vector>

#include "drivers/log.hpp"
#include "drivers/modbus/link_core.hpp"
#include "drivers/modbus/request_screen.hpp"

namespace cellsight::drivers {
namespace {

namespace map = modbus_map;

constexpr const char* kComponent = "modbus";
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr std::int64_t kNsPerS = 1'000'000'000;
// Upper bound on the poll() sleep: the link's periodic work (heartbeat, watchdogs, next result) runs at least this
// often even when no client talks; a publish() wakes the thread at once through the eventfd.
constexpr int kServiceIntervalMs = 20;
constexpr std::int32_t kMaxClientsLimit = 64;
constexpr int kAcceptsPerRound = 16;                // bounds the time one burst of connects can take from serving
constexpr std::size_t kRxBytes = 2 * kMaxAduBytes;  // one whole frame plus the start of a pipelined next one
constexpr std::size_t kPeerNameBytes = INET_ADDRSTRLEN + 8;
// libmodbus's response timeout only matters on its "flush after bad request" path, which screening keeps it from
// taking; keep it tiny anyway so a mistake there cannot sleep the network thread for the default 0.5 s.
constexpr std::uint32_t kLibmodbusResponseTimeoutUs = 1000;
constexpr std::uint32_t kUsPerS = 1'000'000;

std::int64_t monotonic_ns() {
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<std::int64_t>(now.tv_sec) * kNsPerS + now.tv_nsec;
}

struct Client {
  int fd = -1;
  std::array<std::uint8_t, kRxBytes> rx{};
  std::size_t rx_bytes = 0;
  std::int64_t partial_since_ns = 0;  // when the unfinished frame at the front of rx started arriving
  std::int64_t last_activity_ns = 0;
  std::int64_t last_request_ns = 0;  // the last complete request (or the connection) arrived: eviction order
  bool answered = false;             // it has made a complete request since it connected
  std::array<char, kPeerNameBytes> peer{};
};

}  // namespace

struct ModbusServer::Impl {
  explicit Impl(const ModbusServerConfig& cfg) : config(cfg), core(cfg.link) {}

  [[nodiscard]] Status start();
  void stop();
  void run();
  void accept_clients(std::int64_t now_ns);
  void read_client(Client& client, std::int64_t now_ns);
  void serve_frames(Client& client, std::int64_t now_ns);
  void expire_clients(std::int64_t now_ns);
  [[nodiscard]] Client* free_slot(const char* newcomer, std::int64_t now_ns);
  void close_client(Client& client, bool dropped, const char* why);
  void wake() const;

  const ModbusServerConfig config;
  LinkCore core;

  // Network thread only (after start() hands them over by starting the thread).
  modbus_t* ctx = nullptr;
  modbus_mapping_t mapping{};
  std::vector<Client> clients;   // sized at start(), never grows
  std::vector<pollfd> poll_fds;  // listen, wake, then one per client slot
  std::vector<int> poll_client;  // poll_fds index -> clients index
  std::thread thread;

  std::atomic<std::uint64_t> requests_served{0};
  std::atomic<std::uint64_t> exceptions_sent{0};
  std::atomic<std::uint64_t> clients_accepted{0};
  std::atomic<std::uint64_t> clients_refused{0};
  std::atomic<std::uint64_t> clients_evicted{0};
  std::atomic<std::uint64_t> clients_dropped{0};
  std::atomic<std::uint32_t> clients_connected{0};
  int listen_fd = -1;
  std::atomic<int> wake_fd{-1};
  std::atomic<std::uint16_t> port{0};
  std::atomic<bool> running{false};
};

Status ModbusServer::Impl::start() {
  if (running.load()) return make_error("modbus: start() called twice");
  if (config.max_clients < 1 || config.max_clients > kMaxClientsLimit) {
    return make_error("modbus: max_clients must be 1.." + std::to_string(kMaxClientsLimit) + ", got " +
                      std::to_string(config.max_clients));
  }
  if (config.byte_timeout_ms <= 0 || config.idle_timeout_ms < 0) {
    return make_error("modbus: byte_timeout_ms must be > 0 and idle_timeout_ms >= 0");
  }
  in_addr wanted{};
  if (inet_pton(AF_INET, config.bind_address.c_str(), &wanted) != 1) {
    return make_error("modbus: bind address '" + config.bind_address + "' is not a dotted IPv4 address");
  }

  ctx = modbus_new_tcp(config.bind_address.c_str(), config.port);
  if (ctx == nullptr) return make_error(std::string("modbus: modbus_new_tcp failed: ") + modbus_strerror(errno));
  (void)modbus_set_response_timeout(ctx, 0, kLibmodbusResponseTimeoutUs);
  const auto byte_timeout_us = static_cast<std::uint32_t>(config.byte_timeout_ms) * 1000u;
  (void)modbus_set_byte_timeout(ctx, byte_timeout_us / kUsPerS, byte_timeout_us % kUsPerS);

  listen_fd = modbus_tcp_listen(ctx, config.max_clients);
  if (listen_fd < 0) {
    const int err = errno;
    std::string message = "modbus: cannot listen on " + config.bind_address + ":" + std::to_string(config.port) + ": " +
                          std::strerror(err);
    if (err == EACCES && config.port < 1024) {
      message += " (ports below 1024 need CAP_NET_BIND_SERVICE, e.g. AmbientCapabilities= in the systemd unit)";
    } else if (err == EADDRINUSE) {
      message += " (another process holds the port; `ss -ltnp` shows which)";
    }
    stop();
    return make_error(std::move(message));
  }
  // The accept and receive paths never block: one stuck peer must not stall the others.
  (void)fcntl(listen_fd, F_SETFL, fcntl(listen_fd, F_GETFL) | O_NONBLOCK);
  (void)fcntl(listen_fd, F_SETFD, FD_CLOEXEC);

  sockaddr_in bound{};
  socklen_t bound_length = sizeof bound;
  if (getsockname(listen_fd, reinterpret_cast<sockaddr*>(&bound), &bound_length) != 0) {
    const int err = errno;
    stop();
    return make_error(std::string("modbus: getsockname failed: ") + std::strerror(err));
  }
  if (bound.sin_addr.s_addr != wanted.s_addr) {
    // Old libmodbus releases ignore the address and listen everywhere; refuse rather than expose the port.
    stop();
    return make_error("modbus: libmodbus did not bind to " + config.bind_address);
  }
  port.store(ntohs(bound.sin_port));

  const int efd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (efd < 0) {
    const int err = errno;
    stop();
    return make_error(std::string("modbus: eventfd failed: ") + std::strerror(err));
  }
  wake_fd.store(efd);

  // The mapping points into the register image; FC04 sees the same array (read-only blocks only, by screening).
  mapping = modbus_mapping_t{};
  mapping.nb_registers = map::kRegisterSpan;
  mapping.tab_registers = core.registers();
  mapping.nb_input_registers = map::kRegisterSpan;
  mapping.tab_input_registers = core.registers();

  const auto slots = static_cast<std::size_t>(config.max_clients);
  clients.assign(slots, Client{});
  poll_fds.assign(slots + 2, pollfd{});
  poll_client.assign(slots + 2, -1);
  core.reset(monotonic_ns());

  running.store(true);
  try {
    thread = std::thread([this] { run(); });
  } catch (const std::system_error& error) {
    running.store(false);
    stop();
    return make_error(std::string("modbus: cannot start the network thread: ") + error.what());
  }
  CS_LOG_INFO(kComponent, "serving Modbus TCP on %s:%u (max %d clients)", config.bind_address.c_str(),
              static_cast<unsigned>(port.load()), config.max_clients);
  return {};
}

void ModbusServer::Impl::stop() {
  running.store(false);
  wake();
  if (thread.joinable()) thread.join();
  for (Client& client : clients) {
    if (client.fd >= 0) close_client(client, false, "server stopping");
  }
  if (listen_fd >= 0) {
    ::close(listen_fd);
    listen_fd = -1;
  }
  const int efd = wake_fd.exchange(-1);
  if (efd >= 0) ::close(efd);
  if (ctx != nullptr) {
    // ctx's socket is whichever client was answered last, already closed above; modbus_free must not close it
    // again (the number may belong to someone else by now).
    (void)modbus_set_socket(ctx, -1);
    modbus_free(ctx);
    ctx = nullptr;
  }
}

void ModbusServer::Impl::wake() const {
  const int efd = wake_fd.load(std::memory_order_acquire);
  if (efd < 0) return;
  const std::uint64_t one = 1;
  // Non-blocking eventfd: never waits; a full counter (EAGAIN) already means "wake up".
  const ssize_t ignored = ::write(efd, &one, sizeof one);
  (void)ignored;
}

void ModbusServer::Impl::close_client(Client& client, bool dropped, const char* why) {
  CS_LOG_INFO(kComponent, "client %s closed: %s", client.peer.data(), why);
  // Counters first: whoever sees the connection close may look at them right away.
  clients_connected.fetch_sub(1, std::memory_order_relaxed);
  if (dropped) clients_dropped.fetch_add(1, std::memory_order_relaxed);
  ::close(client.fd);
  client.fd = -1;
  client.rx_bytes = 0;
}

void ModbusServer::Impl::accept_clients(std::int64_t now_ns) {
  for (int round = 0; round < kAcceptsPerRound; ++round) {
    sockaddr_in peer{};
    socklen_t peer_length = sizeof peer;
    const int fd = accept4(listen_fd, reinterpret_cast<sockaddr*>(&peer), &peer_length, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR && errno != ECONNABORTED) {
        CS_LOG_WARN(kComponent, "accept failed: %s", std::strerror(errno));
      }
      return;
    }
    std::array<char, kPeerNameBytes> name{};
    char address[INET_ADDRSTRLEN] = "?";
    (void)inet_ntop(AF_INET, &peer.sin_addr, address, sizeof address);
    std::snprintf(name.data(), name.size(), "%s:%u", address, static_cast<unsigned>(ntohs(peer.sin_port)));

    Client* slot = free_slot(name.data(), now_ns);
    if (slot == nullptr) {
      clients_refused.fetch_add(1, std::memory_order_relaxed);
      ::close(fd);
      CS_LOG_WARN(kComponent, "client %s refused: all %d clients are in the middle of a request", name.data(),
                  config.max_clients);
      continue;
    }
    const int one = 1;
    (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);  // replies are single small segments
    slot->fd = fd;
    slot->rx_bytes = 0;
    slot->partial_since_ns = now_ns;
    slot->last_activity_ns = now_ns;
    slot->last_request_ns = now_ns;
    slot->answered = false;
    slot->peer = name;
    clients_accepted.fetch_add(1, std::memory_order_relaxed);
    clients_connected.fetch_add(1, std::memory_order_relaxed);
    CS_LOG_INFO(kComponent, "client %s connected", name.data());
  }
}

// An empty slot, else a slot closed for the newcomer: of a client that has made no request since it connected (the
// one connected longest), else of the client longest without a complete request. Idle holders (a crashed HMI, a port
// scanner, an attacker) must not lock a reconnecting PLC out until the idle timeout, and a storm of new connections
// that send nothing must not push out a client that polls, however briefly that one has been quiet (the soak found
// a polling PLC evicted by every burst of port-scan connections). A client with half a request buffered is left
// alone: it is working, and it finishes or is dropped within byte_timeout_ms. nullptr when every client is such a one.
Client* ModbusServer::Impl::free_slot(const char* newcomer, std::int64_t now_ns) {
  Client* victim = nullptr;
  const auto before = [](const Client& a, const Client& b) {
    if (a.answered != b.answered) return !a.answered;
    return a.last_request_ns < b.last_request_ns;
  };
  for (Client& client : clients) {
    if (client.fd < 0) return &client;
    if (client.rx_bytes > 0) continue;
    if (victim == nullptr || before(client, *victim)) victim = &client;
  }
  if (victim == nullptr) return nullptr;
  const double idle_s = static_cast<double>(now_ns - victim->last_request_ns) / kNsPerS;
  CS_LOG_WARN(kComponent, "client %s evicted: %s %.3f s, %s of %d clients; its slot goes to %s", victim->peer.data(),
              victim->answered ? "no request for" : "no request since it connected", idle_s,
              victim->answered ? "the longest" : "the longest silent newcomer", config.max_clients, newcomer);
  clients_evicted.fetch_add(1, std::memory_order_relaxed);
  close_client(
      *victim, false,
      victim->answered ? "evicted (longest idle, table full)" : "evicted (no request since it connected, table full)");
  return victim;
}

void ModbusServer::Impl::read_client(Client& client, std::int64_t now_ns) {
  const ssize_t got =
      recv(client.fd, client.rx.data() + client.rx_bytes, client.rx.size() - client.rx_bytes, MSG_DONTWAIT);
  if (got == 0) {
    close_client(client, false, "peer closed the connection");
    return;
  }
  if (got < 0) {
    if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return;
    close_client(client, true, std::strerror(errno));
    return;
  }
  if (client.rx_bytes == 0) client.partial_since_ns = now_ns;
  client.rx_bytes += static_cast<std::size_t>(got);
  client.last_activity_ns = now_ns;
  serve_frames(client, now_ns);
}

void ModbusServer::Impl::serve_frames(Client& client, std::int64_t now_ns) {
  std::size_t offset = 0;
  while (client.fd >= 0) {
    const std::span<const std::uint8_t> pending(client.rx.data() + offset, client.rx_bytes - offset);
    const ScreenResult screened = screen_request(pending);
    if (screened.verdict == ScreenVerdict::kIncomplete) break;
    if (screened.verdict == ScreenVerdict::kClose) {
      const char* why = screened.close_reason == CloseReason::kProtocolId       ? "protocol id is not Modbus (0)"
                        : screened.close_reason == CloseReason::kLengthTooShort ? "MBAP length below 2"
                                                                                : "MBAP length above 254";
      close_client(client, true, why);
      return;
    }
    core.service(now_ns);  // the reply shows the state as of now (heartbeat, RESULT_VALID, next result)
    if (screened.verdict == ScreenVerdict::kException) {
      std::array<std::uint8_t, kExceptionReplyBytes> reply{};
      build_exception_reply(pending, screened.exception_code, reply);
      CS_LOG_DEBUG(kComponent, "client %s: function 0x%02x address %u quantity %u -> exception %u", client.peer.data(),
                   screened.function, screened.address, screened.quantity, screened.exception_code);
      if (send(client.fd, reply.data(), reply.size(), MSG_NOSIGNAL | MSG_DONTWAIT) !=
          static_cast<ssize_t>(reply.size())) {
        close_client(client, true, "cannot send (peer not reading)");
        return;
      }
      exceptions_sent.fetch_add(1, std::memory_order_relaxed);
      client.last_request_ns = now_ns;
      client.answered = true;
    } else {
      (void)modbus_set_socket(ctx, client.fd);
      if (modbus_reply(ctx, pending.data(), static_cast<int>(screened.frame_bytes), &mapping) < 0) {
        close_client(client, true, "cannot send (peer not reading)");
        return;
      }
      requests_served.fetch_add(1, std::memory_order_relaxed);
      client.last_request_ns = now_ns;
      client.answered = true;
      if (is_write_function(screened.function)) {
        core.on_plc_write(now_ns);
        core.service(now_ns);  // an ack or a cleared ack takes effect before the next request is read
      }
    }
    offset += screened.frame_bytes;
  }
  if (client.fd < 0 || offset == 0) return;
  client.rx_bytes -= offset;
  std::memmove(client.rx.data(), client.rx.data() + offset, client.rx_bytes);
  client.partial_since_ns = now_ns;
}

void ModbusServer::Impl::expire_clients(std::int64_t now_ns) {
  for (Client& client : clients) {
    if (client.fd < 0) continue;
    if (client.rx_bytes > 0 && now_ns - client.partial_since_ns > config.byte_timeout_ms * kNsPerMs) {
      close_client(client, true, "byte timeout inside a request");
    } else if (config.idle_timeout_ms > 0 && now_ns - client.last_activity_ns > config.idle_timeout_ms * kNsPerMs) {
      close_client(client, true, "idle timeout");
    }
  }
}

void ModbusServer::Impl::run() {
  const int efd = wake_fd.load();
  while (running.load(std::memory_order_acquire)) {
    std::size_t count = 0;
    poll_fds[count++] = pollfd{listen_fd, POLLIN, 0};
    poll_fds[count++] = pollfd{efd, POLLIN, 0};
    for (std::size_t i = 0; i < clients.size(); ++i) {
      if (clients[i].fd < 0) continue;
      poll_client[count] = static_cast<int>(i);
      poll_fds[count++] = pollfd{clients[i].fd, POLLIN, 0};
    }
    // Wake early enough to enforce the byte timeout of a half-received frame.
    int timeout_ms = kServiceIntervalMs;
    if (config.byte_timeout_ms < timeout_ms) timeout_ms = config.byte_timeout_ms;
    const int ready = poll(poll_fds.data(), count, timeout_ms);
    const std::int64_t now = monotonic_ns();
    if (ready < 0 && errno != EINTR) {
      CS_LOG_ERROR(kComponent, "poll failed: %s", std::strerror(errno));
      std::this_thread::sleep_for(std::chrono::milliseconds(kServiceIntervalMs));  // no busy loop on a persistent error
    }
    if (ready > 0) {
      if ((poll_fds[1].revents & POLLIN) != 0) {
        std::uint64_t drained = 0;
        const ssize_t ignored = ::read(efd, &drained, sizeof drained);
        (void)ignored;
      }
      for (std::size_t i = 2; i < count; ++i) {
        if ((poll_fds[i].revents & (POLLIN | POLLHUP | POLLERR)) == 0) continue;
        Client& client = clients[static_cast<std::size_t>(poll_client[i])];
        if (client.fd == poll_fds[i].fd) read_client(client, now);
      }
      if ((poll_fds[0].revents & POLLIN) != 0) accept_clients(now);
    }
    expire_clients(now);
    core.service(now);
  }
}

// ---------------------------------------------------------------- PlcLink

ModbusServer::ModbusServer(const ModbusServerConfig& config) : impl_(std::make_unique<Impl>(config)) {}
ModbusServer::~ModbusServer() {
  stop();
}

Status ModbusServer::start() {
  return impl_->start();
}
void ModbusServer::stop() {
  impl_->stop();
}
std::uint16_t ModbusServer::bound_port() const {
  return impl_->port.load();
}

PublishStatus ModbusServer::publish(const PlcResult& result) {
  const PublishStatus status = impl_->core.publish(result);
  if (status == PublishStatus::kQueued) impl_->wake();  // present it now rather than at the next service tick
  return status;
}
void ModbusServer::set_flag(StatusFlag flag, bool on) {
  impl_->core.set_flag(flag, on);
}
void ModbusServer::set_error(ErrorCode code) {
  impl_->core.set_error(code);
  impl_->wake();
}
void ModbusServer::set_warning(WarningCode code) {
  impl_->core.set_warning(code);
}
void ModbusServer::set_active_models(std::uint16_t database_id) {
  impl_->core.set_active_models(database_id);
}
void ModbusServer::set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers) {
  impl_->core.set_trigger_counters(trigger_count, missed_triggers);
}
void ModbusServer::complete_command(bool ok) {
  impl_->core.complete_command(ok);
}
PlcCommands ModbusServer::take_commands() {
  return impl_->core.take_commands();
}
void ModbusServer::heartbeat() {
  impl_->core.heartbeat(monotonic_ns());
}

LinkStats ModbusServer::stats() const {
  LinkStats stats = impl_->core.stats();
  stats.requests_served = impl_->requests_served.load(std::memory_order_relaxed);
  stats.exceptions_sent = impl_->exceptions_sent.load(std::memory_order_relaxed);
  stats.clients_accepted = impl_->clients_accepted.load(std::memory_order_relaxed);
  stats.clients_refused = impl_->clients_refused.load(std::memory_order_relaxed);
  stats.clients_evicted = impl_->clients_evicted.load(std::memory_order_relaxed);
  stats.clients_dropped = impl_->clients_dropped.load(std::memory_order_relaxed);
  stats.clients_connected = impl_->clients_connected.load(std::memory_order_relaxed);
  return stats;
}

}  // namespace cellsight::drivers
