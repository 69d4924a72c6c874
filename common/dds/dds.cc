// The non-template half of the RAII wrapper over Cyclone DDS's C API (dds.h): errors, the loopback
// configuration, domains, QoS and participants.
#include "common/dds/dds.h"

#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <string>

namespace somasim::dds {

namespace {

// The largest automatic participant index whose unicast ports stay inside the domain's block of
// 250 ports (DDSI port mapping: d1 = 10 + 2·index, d3 = 11 + 2·index above the domain base).
constexpr int kMaxAutoParticipantIndex = 119;

// Says what a failing dds_create_domain most likely means; the precise reason (the offending
// element or interface) is only in Cyclone's log, which Domain captures.
std::string DomainFailureHint(dds_return_t code) {
  switch (code) {
    case DDS_RETCODE_PRECONDITION_NOT_MET:
      return " (a domain with this id already exists in this process: one Domain per id, and "
             "no Participant of that id may exist before it)";
    case DDS_RETCODE_BAD_PARAMETER:
      return " (bad domain id)";
    case DDS_RETCODE_ERROR:
      return " (Cyclone rejected the configuration: malformed XML, an unknown element or value, "
             "a network interface that does not exist, or text not starting with '<' that is "
             "no readable file)";
    default:
      return "";
  }
}

// Collects what Cyclone logs for one domain while it is being created, so that the DdsError can
// say which element, value or interface was wrong (dds_create_domain returns only "Error").
struct LogCapture {
  std::string text;  // messages separated by "; "
};

// In 0.10.2 the sink gets `message` without its header (size is the message's length) and a
// `domid` that is not reliably set during configuration, so it cannot filter by domain: anything
// another thread logs meanwhile lands here too, which is rare and harmless.
void CaptureLog(void* user, const dds_log_data_t* data) {
  auto* capture = static_cast<LogCapture*>(user);
  std::string message(data->message, data->size);
  while (!message.empty() && (message.back() == '\n' || message.back() == ' ')) {
    message.pop_back();
  }
  if (message.empty()) return;
  if (!capture->text.empty()) capture->text += "; ";
  capture->text += message;
}

// Cyclone's log sink is process-wide: one domain creation captures it at a time.
std::mutex log_capture_mutex;

}  // namespace

DdsError::DdsError(const std::string& what, dds_return_t code)
    : std::runtime_error(what + ": " + dds_strretcode(code)), code_(code) {}

std::string LoopbackConfig(int max_participants) {
  if (max_participants < 1 || max_participants > kMaxAutoParticipantIndex + 1) {
    throw DdsError("LoopbackConfig: max_participants " + std::to_string(max_participants) +
                       " is outside 1.." + std::to_string(kMaxAutoParticipantIndex + 1),
                   DDS_RETCODE_BAD_PARAMETER);
  }
  // Multicast is off on `lo`, so discovery is unicast: every participant takes a free index
  // (its own unicast port) and announces itself (SPDP) to the ports of indices
  // 0..MaxAutoParticipantIndex on 127.0.0.1, which is how processes on this host find each other.
  // Cyclone's default 1344-byte fragments stay: 62000-byte ones (loopback's MTU allows them) cut
  // the frame latency p50 from 0.31 to 0.22 ms, but a killed peer then slowed the server's
  // physics by a quarter until its lease ran out (ServerOverDds.KillingTheMockNode... failed 3 of
  // 5 runs, 0 of 5 without).
  return "<CycloneDDS><Domain id=\"any\">"
         "<General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces>"
         "<AllowMulticast>false</AllowMulticast>"
         "</General>"
         "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
         "<MaxAutoParticipantIndex>" +
         std::to_string(max_participants - 1) +
         "</MaxAutoParticipantIndex>"
         "<Peers><Peer address=\"127.0.0.1\"/></Peers></Discovery>"
         "</Domain></CycloneDDS>";
}

Domain::Domain(uint32_t domain_id, const std::string& config_xml) : id_(domain_id), handle_(0) {
  // dds_create_domain does not read CYCLONEDDS_URI itself; "" means what a Participant without
  // a Domain would get (the environment's configuration, else Cyclone's defaults).
  std::string config = config_xml;
  if (config.empty()) {
    if (const char* uri = std::getenv("CYCLONEDDS_URI"); uri != nullptr) config = uri;
  }
  // Cyclone closes elements still open at the end of the text, so it would take a truncated
  // profile (a half-written file) for a complete one; catch the common case here.
  const size_t first = config.find_first_not_of(" \t\r\n");
  if (first != std::string::npos && config[first] == '<' &&
      config.find("<CycloneDDS") != std::string::npos &&
      config.find("</CycloneDDS>") == std::string::npos &&
      config.find("<CycloneDDS/>") == std::string::npos) {
    throw DdsError("dds_create_domain(domain " + std::to_string(domain_id) +
                       "): the configuration XML is truncated: <CycloneDDS> is never closed",
                   DDS_RETCODE_BAD_PARAMETER);
  }
  LogCapture capture;
  {
    const std::lock_guard<std::mutex> lock(log_capture_mutex);
    dds_set_log_sink(&CaptureLog, &capture);
    handle_ = dds_create_domain(domain_id, config.c_str());
    dds_set_log_sink(nullptr, nullptr);  // back to Cyclone's default (stderr)
  }
  if (handle_ < 0) {
    throw DdsError("dds_create_domain(domain " + std::to_string(domain_id) + ")" +
                       DomainFailureHint(handle_) +
                       (capture.text.empty() ? "" : " [Cyclone: " + capture.text + "]"),
                   handle_);
  }
  // Warnings of a domain that works (e.g. multicast disabled on an interface) still belong on
  // stderr, where Cyclone would have written them.
  if (!capture.text.empty()) std::fprintf(stderr, "cyclonedds: %s\n", capture.text.c_str());
}

Domain::~Domain() { dds_delete(handle_); }

Qos::Qos() : qos_(dds_create_qos()) {}

Qos::~Qos() { dds_delete_qos(qos_); }

Qos::Qos(const Qos& other) : qos_(dds_create_qos()) { dds_copy_qos(qos_, other.qos_); }

Qos& Qos::operator=(const Qos& other) {
  if (this != &other) {
    // dds_copy_qos overwrites without freeing what the destination held (partition strings).
    dds_reset_qos(qos_);
    dds_copy_qos(qos_, other.qos_);
  }
  return *this;
}

Qos& Qos::Reliable(std::chrono::milliseconds max_blocking) {
  dds_qset_reliability(qos_, DDS_RELIABILITY_RELIABLE, DDS_MSECS(max_blocking.count()));
  return *this;
}

Qos& Qos::BestEffort() {
  dds_qset_reliability(qos_, DDS_RELIABILITY_BEST_EFFORT, 0);
  return *this;
}

Qos& Qos::Volatile() {
  dds_qset_durability(qos_, DDS_DURABILITY_VOLATILE);
  return *this;
}

Qos& Qos::TransientLocal() {
  dds_qset_durability(qos_, DDS_DURABILITY_TRANSIENT_LOCAL);
  return *this;
}

Qos& Qos::KeepLast(int32_t depth) {
  dds_qset_history(qos_, DDS_HISTORY_KEEP_LAST, depth);
  return *this;
}

Qos& Qos::KeepAll() {
  dds_qset_history(qos_, DDS_HISTORY_KEEP_ALL, DDS_LENGTH_UNLIMITED);
  return *this;
}

Qos& Qos::DurabilityService(int32_t depth, int32_t max_instances) {
  // Cyclone serves transient-local late joiners from the writer's history cache, kept to this
  // depth per instance; max_samples is what `depth` per instance needs, no more.
  dds_qset_durability_service(qos_, 0, DDS_HISTORY_KEEP_LAST, depth, depth * max_instances,
                              max_instances, depth);
  return *this;
}

Qos& Qos::Deadline(std::chrono::milliseconds period) {
  dds_qset_deadline(qos_, DDS_MSECS(period.count()));
  return *this;
}

Qos& Qos::ManualLiveliness(std::chrono::milliseconds lease) {
  dds_qset_liveliness(qos_, DDS_LIVELINESS_MANUAL_BY_TOPIC, DDS_MSECS(lease.count()));
  return *this;
}

Qos& Qos::AutomaticLiveliness(std::chrono::milliseconds lease) {
  dds_qset_liveliness(qos_, DDS_LIVELINESS_AUTOMATIC, DDS_MSECS(lease.count()));
  return *this;
}

Qos& Qos::Partition(const std::string& name) {
  dds_qset_partition1(qos_, name.c_str());
  return *this;
}

Participant::Participant(uint32_t domain_id)
    : handle_(dds_create_participant(domain_id, nullptr, nullptr)) {
  if (handle_ < 0) {
    throw DdsError("dds_create_participant(domain " + std::to_string(domain_id) + ")", handle_);
  }
}

Participant::~Participant() { dds_delete(handle_); }

}  // namespace somasim::dds
