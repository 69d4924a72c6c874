// Small RAII C++ types over Cyclone DDS's C API (Debian's Cyclone is C only; SPEC §1, §3):
// a domain with its own configuration, a participant, QoS, topics, writers and readers of the
// idlc-generated C types (idl/*.idl, target somasim::wire). Every entity is deleted by its
// destructor; every failing call throws DdsError naming the call and Cyclone's reason.
//
// Partitions: writers and readers take the session's partition name (`--session NAME`), so two
// sessions on one domain never see each other's samples.
#pragma once

#include <dds/dds.h>

#include <chrono>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <utility>

namespace somasim::dds {

class DdsError : public std::runtime_error {
 public:
  // what(): "<what>: <dds_strretcode(code)>".
  DdsError(const std::string& what, dds_return_t code);
  dds_return_t code() const { return code_; }

 private:
  dds_return_t code_;
};

// Cyclone configuration XML (the <CycloneDDS> document, or "" for Cyclone's defaults and the
// CYCLONEDDS_URI environment variable).
// Loopback only: interface "lo", multicast off, unicast discovery to 127.0.0.1 with automatic
// participant indices. Cyclone gives one index to each process's domain (all participants of a
// process share it), so max_participants bounds the PROCESSES of this domain on this host;
// 1..120 (the ports must stay in the domain's block), else DdsError. Same content as
// deploy/cyclonedds-loopback.xml.
std::string LoopbackConfig(int max_participants = 32);

// A domain created with an explicit configuration (dds_create_domain); tests use one per test
// with their own domain id, so `ctest -j` cannot cross them. Without a Domain object a
// Participant uses Cyclone's default configuration for its domain id.
// config_xml: the XML text, or (not starting with '<') a file name / file:// URI, or "" (then
// CYCLONEDDS_URI, else Cyclone's defaults). Throws DdsError with Cyclone's own reason (its log,
// e.g. "NoSuchElement: unknown element", "no_such_if9: does not match an available interface")
// for a rejected configuration, DDS_RETCODE_BAD_PARAMETER for XML whose <CycloneDDS> is never
// closed (Cyclone itself would accept it truncated), and DDS_RETCODE_PRECONDITION_NOT_MET when
// the id already has a domain in this process (a second Domain, or a Participant created first).
// Destroying the Domain deletes every entity in it: declare it before its participants.
class Domain {
 public:
  Domain(uint32_t domain_id, const std::string& config_xml);
  ~Domain();
  Domain(const Domain&) = delete;
  Domain& operator=(const Domain&) = delete;
  uint32_t id() const { return id_; }

 private:
  uint32_t id_;
  dds_entity_t handle_;
};

// QoS, built fluently: Qos().Reliable().TransientLocal().KeepLast(1).
class Qos {
 public:
  Qos();
  ~Qos();
  Qos(const Qos& other);
  Qos& operator=(const Qos& other);
  Qos& Reliable(std::chrono::milliseconds max_blocking = std::chrono::milliseconds(0));
  Qos& BestEffort();
  Qos& Volatile();
  Qos& TransientLocal();
  Qos& KeepLast(int32_t depth);
  Qos& KeepAll();
  // Durability service of a transient-local writer: the history it serves late joiners from
  // (keep-last `depth` per instance, up to `max_instances` instances).
  Qos& DurabilityService(int32_t depth, int32_t max_instances);
  // Requested (reader) period must be >= offered (writer) period, or the two never match; the
  // reader counts one miss per period per instance without a sample.
  Qos& Deadline(std::chrono::milliseconds period);
  // Manual-by-topic liveliness: each write (or AssertLiveliness) renews a `lease`. Measured with
  // Cyclone 0.10.2 on loopback (dds_test), best-effort and reliable writers alike, in the same
  // process and from another process: a reader counts the writer alive from its first write or
  // assertion, keeps it alive while it asserts (every lease/4) without writing, and reports it
  // not alive (alive_writers 0, not_alive_writers 1) ~1 lease (+0..5 ms) after the last
  // renewal, while matched_writers stays 1; the next write makes it alive again. The reader's
  // requested lease must be >= the writer's offered one, or the two never match.
  Qos& ManualLiveliness(std::chrono::milliseconds lease);
  Qos& AutomaticLiveliness(std::chrono::milliseconds lease);
  Qos& Partition(const std::string& name);
  const dds_qos_t* get() const { return qos_; }

 private:
  dds_qos_t* qos_;
};

class Participant {
 public:
  explicit Participant(uint32_t domain_id);
  ~Participant();
  Participant(const Participant&) = delete;
  Participant& operator=(const Participant&) = delete;
  dds_entity_t handle() const { return handle_; }

 private:
  dds_entity_t handle_;
};

// A topic of the idlc type T (e.g. somasim_wire_MeshFrame with somasim_wire_MeshFrame_desc).
template <typename T>
class Topic {
 public:
  Topic(const Participant& participant, const dds_topic_descriptor_t& descriptor,
        const std::string& name, const Qos& qos = Qos());
  ~Topic();
  Topic(const Topic&) = delete;
  Topic& operator=(const Topic&) = delete;
  dds_entity_t handle() const { return handle_; }
  const std::string& name() const { return name_; }

 private:
  dds_entity_t handle_;
  std::string name_;
};

// A writer in the partition `qos` names (through its own publisher).
template <typename T>
class Writer {
 public:
  Writer(const Participant& participant, const Topic<T>& topic, const Qos& qos);
  ~Writer();
  Writer(const Writer&) = delete;
  Writer& operator=(const Writer&) = delete;
  // Throws DdsError on failure (a best-effort writer never blocks; a reliable one blocks at most
  // its max_blocking time and then throws with DDS_RETCODE_TIMEOUT). Writing does not wait for
  // discovery: a sample written before a reader has matched is not delivered to it (unless
  // transient-local), so wait for MatchedReaders() first when that matters.
  void Write(const T& sample);
  // Like Write, but returns Cyclone's code instead of throwing (for loops that count failures).
  dds_return_t TryWrite(const T& sample);
  void AssertLiveliness();
  // Readers currently matched (dds_get_publication_matched_status).
  int32_t MatchedReaders() const;
  dds_entity_t handle() const { return handle_; }

 private:
  dds_entity_t publisher_;
  dds_entity_t handle_;
};

// Counters of what a reader has been told (requested deadline missed, liveliness changed,
// samples lost or rejected by Cyclone), cumulative since creation; matched/alive/not-alive are
// current counts, not totals.
struct ReaderStatus {
  int32_t matched_writers = 0;
  int32_t alive_writers = 0;  // liveliness: writers currently alive
  int32_t not_alive_writers = 0;
  uint32_t deadline_missed = 0;  // total requested-deadline-missed count
  uint32_t samples_lost = 0;
  uint32_t samples_rejected = 0;
};

// A reader in the partition `qos` names (through its own subscriber).
template <typename T>
class Reader {
 public:
  Reader(const Participant& participant, const Topic<T>& topic, const Qos& qos);
  ~Reader();
  Reader(const Reader&) = delete;
  Reader& operator=(const Reader&) = delete;
  // Takes up to `max` samples (loaned from Cyclone, returned before this returns) and calls
  // fn(const T&, const dds_sample_info_t&) for each valid one, oldest first. Returns how many it
  // passed to fn. Never blocks.
  template <typename Fn>
  int Take(Fn&& fn, int max = 64);
  // Blocks until data is available or `timeout` passes; true when data is available.
  bool WaitForData(std::chrono::milliseconds timeout);
  ReaderStatus Status();
  dds_entity_t handle() const { return handle_; }

 private:
  dds_entity_t subscriber_;
  dds_entity_t handle_;
  dds_entity_t read_condition_;  // any sample state; attached to waitset_
  dds_entity_t waitset_;
  uint32_t deadline_missed_ = 0;
  uint32_t samples_lost_ = 0;
  uint32_t samples_rejected_ = 0;
};

// Copies a std::string into an idlc string field (char*) that Cyclone frees with the sample:
// for samples this process writes, the caller keeps the std::string alive until after Write.
inline char* CString(const std::string& s) { return const_cast<char*>(s.c_str()); }

}  // namespace somasim::dds

#include "common/dds/dds_impl.h"  // the templates' definitions
