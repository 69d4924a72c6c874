#include "server/net/endpoints.h"

namespace somasim::net {

Endpoints::Endpoints(uint32_t domain, const std::string& config, const std::string& s,
                     bool rigid_bodies)
    : domain_config(config.empty() ? nullptr : std::make_unique<dds::Domain>(domain, config)),
      participant(domain),
      topics(participant),
      session(participant, topics.session, dds::SessionQos(s)),
      topology(participant, topics.topology, dds::TopologyQos(s)),
      frame(participant, topics.frame, dds::FrameQos(s)),
      force_model(participant, topics.force_model, dds::ForceModelQos(s)),
      event(participant, topics.event, dds::EventQos(s)),
      heartbeat(participant, topics.heartbeat, dds::HeartbeatQos(s)),
      metrics(participant, topics.metrics, dds::MetricsQos(s)),
      rigid_body(rigid_bodies ? std::make_unique<dds::Writer<somasim_wire_RigidBodyState>>(
                                    participant, topics.rigid_body, dds::RigidBodyQos(s))
                              : nullptr),
      tool_command(participant, topics.tool_command, dds::ToolCommandQos(s)),
      instructor(participant, topics.instructor, dds::InstructorQos(s)) {}

}  // namespace somasim::net
