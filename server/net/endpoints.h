// The server's DDS entities in its session's partition (SPEC §3, docs/topics.md): one
// participant, its topics, and a writer or reader for each topic the server speaks. Made once at
// start-up; Cyclone's writers and readers may be used from the publisher and the tool link's
// threads at once.
#pragma once

#include <memory>
#include <string>

#include "common/dds/topics.h"

namespace somasim::net {

struct Endpoints {
  // `config`: Cyclone XML ("" = CYCLONEDDS_URI or Cyclone's defaults). `rigid_bodies`: make the
  // rigid-body writer (a session with stones). Throws dds::DdsError.
  Endpoints(uint32_t domain, const std::string& config, const std::string& session,
            bool rigid_bodies);

  std::unique_ptr<dds::Domain> domain_config;  // declared first: destroyed last
  dds::Participant participant;
  dds::Topics topics;
  dds::Writer<somasim_wire_SessionInfo> session;
  dds::Writer<somasim_wire_OrganTopology> topology;
  dds::Writer<somasim_wire_MeshFrame> frame;
  dds::Writer<somasim_wire_ForceModel> force_model;
  dds::Writer<somasim_wire_SessionEvent> event;
  dds::Writer<somasim_wire_Heartbeat> heartbeat;
  dds::Writer<somasim_wire_ServerMetrics> metrics;
  std::unique_ptr<dds::Writer<somasim_wire_RigidBodyState>> rigid_body;  // none: no bodies
  dds::Reader<somasim_wire_ToolCommand> tool_command;
  dds::Reader<somasim_wire_InstructorCommand> instructor;
};

}  // namespace somasim::net
