// The templates' definitions for dds.h (Topic, Writer, Reader); included at its end only.
#pragma once

#include <algorithm>
#include <string>

namespace somasim::dds {

namespace internal {

// Returns a reader's loaned samples even when the caller's function throws.
class LoanGuard {
 public:
  LoanGuard(dds_entity_t reader, void** samples, int32_t count)
      : reader_(reader), samples_(samples), count_(count) {}
  ~LoanGuard() { dds_return_loan(reader_, samples_, count_); }
  LoanGuard(const LoanGuard&) = delete;
  LoanGuard& operator=(const LoanGuard&) = delete;

 private:
  dds_entity_t reader_;
  void** samples_;
  int32_t count_;
};

}  // namespace internal

// --- Topic ---------------------------------------------------------------------------------------

template <typename T>
Topic<T>::Topic(const Participant& participant, const dds_topic_descriptor_t& descriptor,
                const std::string& name, const Qos& qos)
    : handle_(0), name_(name) {
  if (name.empty()) {
    throw DdsError("Topic: empty topic name (type " + std::string(descriptor.m_typename) + ")",
                   DDS_RETCODE_BAD_PARAMETER);
  }
  // A descriptor of another type would make Cyclone read and write T's memory with the wrong
  // layout; its size is the cheap check that catches the mix-up.
  if (descriptor.m_size != sizeof(T)) {
    throw DdsError("Topic \"" + name + "\": descriptor of " + descriptor.m_typename + " (" +
                       std::to_string(descriptor.m_size) + " bytes) does not describe a type of " +
                       std::to_string(sizeof(T)) + " bytes",
                   DDS_RETCODE_BAD_PARAMETER);
  }
  handle_ = dds_create_topic(participant.handle(), &descriptor, name.c_str(), qos.get(), nullptr);
  if (handle_ < 0) {
    throw DdsError("dds_create_topic(\"" + name + "\", " + descriptor.m_typename + ")", handle_);
  }
}

template <typename T>
Topic<T>::~Topic() {
  dds_delete(handle_);
}

// --- Writer --------------------------------------------------------------------------------------

template <typename T>
Writer<T>::Writer(const Participant& participant, const Topic<T>& topic, const Qos& qos)
    : publisher_(0), handle_(0) {
  // Partition is a publisher policy; Cyclone takes only the publisher's policies from `qos` here
  // and only the writer's policies below.
  publisher_ = dds_create_publisher(participant.handle(), qos.get(), nullptr);
  if (publisher_ < 0) {
    throw DdsError("dds_create_publisher(for topic \"" + topic.name() + "\")", publisher_);
  }
  handle_ = dds_create_writer(publisher_, topic.handle(), qos.get(), nullptr);
  if (handle_ < 0) {
    const dds_return_t code = handle_;
    dds_delete(publisher_);
    throw DdsError("dds_create_writer(topic \"" + topic.name() + "\")", code);
  }
}

template <typename T>
Writer<T>::~Writer() {
  dds_delete(publisher_);  // and the writer with it
}

template <typename T>
void Writer<T>::Write(const T& sample) {
  const dds_return_t code = dds_write(handle_, &sample);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_write", code);
}

template <typename T>
dds_return_t Writer<T>::TryWrite(const T& sample) {
  return dds_write(handle_, &sample);
}

template <typename T>
void Writer<T>::AssertLiveliness() {
  const dds_return_t code = dds_assert_liveliness(handle_);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_assert_liveliness", code);
}

template <typename T>
int32_t Writer<T>::MatchedReaders() const {
  dds_publication_matched_status_t status;
  const dds_return_t code = dds_get_publication_matched_status(handle_, &status);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_publication_matched_status", code);
  return static_cast<int32_t>(status.current_count);
}

// --- Reader --------------------------------------------------------------------------------------

template <typename T>
Reader<T>::Reader(const Participant& participant, const Topic<T>& topic, const Qos& qos)
    : subscriber_(0), handle_(0), read_condition_(0), waitset_(0) {
  subscriber_ = dds_create_subscriber(participant.handle(), qos.get(), nullptr);
  if (subscriber_ < 0) {
    throw DdsError("dds_create_subscriber(for topic \"" + topic.name() + "\")", subscriber_);
  }
  // Everything below is the subscriber's child or deleted explicitly on failure.
  const auto fail = [&](const char* call, dds_return_t code) {
    if (waitset_ > 0) dds_delete(waitset_);
    dds_delete(subscriber_);
    throw DdsError(std::string(call) + "(topic \"" + topic.name() + "\")", code);
  };
  handle_ = dds_create_reader(subscriber_, topic.handle(), qos.get(), nullptr);
  if (handle_ < 0) fail("dds_create_reader", handle_);
  read_condition_ = dds_create_readcondition(handle_, DDS_ANY_STATE);
  if (read_condition_ < 0) fail("dds_create_readcondition", read_condition_);
  waitset_ = dds_create_waitset(participant.handle());
  if (waitset_ < 0) fail("dds_create_waitset", waitset_);
  const dds_return_t code = dds_waitset_attach(waitset_, read_condition_, read_condition_);
  if (code != DDS_RETCODE_OK) fail("dds_waitset_attach", code);
}

template <typename T>
Reader<T>::~Reader() {
  dds_delete(waitset_);
  dds_delete(subscriber_);  // and the reader and its read condition with it
}

template <typename T>
template <typename Fn>
int Reader<T>::Take(Fn&& fn, int max) {
  // Fixed-size batches on the stack: the only allocations are Cyclone's (its reader loan buffer,
  // reused from call to call, and the samples' sequences).
  constexpr int kBatch = 64;
  void* samples[kBatch];
  dds_sample_info_t infos[kBatch];
  int passed = 0;
  int remaining = max;
  while (remaining > 0) {
    const int batch = std::min(remaining, kBatch);
    std::fill(samples, samples + batch, nullptr);  // null: Cyclone lends the samples
    const dds_return_t n =
        dds_take(handle_, samples, infos, static_cast<size_t>(batch), static_cast<uint32_t>(batch));
    if (n < 0) throw DdsError("dds_take", n);
    if (n == 0) break;
    {
      const internal::LoanGuard loan(handle_, samples, n);
      for (int i = 0; i < n; ++i) {
        // Invalid samples only say that an instance was disposed or lost its writers.
        if (!infos[i].valid_data) continue;
        fn(*static_cast<const T*>(samples[i]), static_cast<const dds_sample_info_t&>(infos[i]));
        ++passed;
      }
    }
    remaining -= n;
    if (n < batch) break;
  }
  return passed;
}

template <typename T>
bool Reader<T>::WaitForData(std::chrono::milliseconds timeout) {
  const dds_return_t n = dds_waitset_wait(waitset_, nullptr, 0, DDS_MSECS(timeout.count()));
  if (n < 0) throw DdsError("dds_waitset_wait", n);
  return n > 0;
}

template <typename T>
ReaderStatus Reader<T>::Status() {
  dds_subscription_matched_status_t matched;
  dds_liveliness_changed_status_t liveliness;
  dds_requested_deadline_missed_status_t deadline;
  dds_sample_lost_status_t lost;
  dds_sample_rejected_status_t rejected;
  dds_return_t code = dds_get_subscription_matched_status(handle_, &matched);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_subscription_matched_status", code);
  code = dds_get_liveliness_changed_status(handle_, &liveliness);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_liveliness_changed_status", code);
  code = dds_get_requested_deadline_missed_status(handle_, &deadline);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_requested_deadline_missed_status", code);
  code = dds_get_sample_lost_status(handle_, &lost);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_sample_lost_status", code);
  code = dds_get_sample_rejected_status(handle_, &rejected);
  if (code != DDS_RETCODE_OK) throw DdsError("dds_get_sample_rejected_status", code);
  // The get_ calls reset only the *_change fields; total_count is cumulative in Cyclone, so the
  // totals are the cumulative counters themselves.
  deadline_missed_ = deadline.total_count;
  samples_lost_ = lost.total_count;
  samples_rejected_ = rejected.total_count;
  ReaderStatus status;
  status.matched_writers = static_cast<int32_t>(matched.current_count);
  status.alive_writers = static_cast<int32_t>(liveliness.alive_count);
  status.not_alive_writers = static_cast<int32_t>(liveliness.not_alive_count);
  status.deadline_missed = deadline_missed_;
  status.samples_lost = samples_lost_;
  status.samples_rejected = samples_rejected_;
  return status;
}

}  // namespace somasim::dds
