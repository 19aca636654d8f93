// The participant QoS the DDS participants made from now on start with.
//
// Why: in the per-node profile every node process has a DDS participant of
// its own, and every participant re-announces itself to every other one
// each lease-announcement period. The project's profile sets that period to
// 100 ms so that a fresh `ros2` process finds the *container* within its
// 0.5 s (fixtures/fastdds_no_shm.xml says why); applied to N node
// participants it costs N x N announcements every 100 ms, most of an idle
// per-node container's CPU (bench.scale). Only the container's own
// participant needs to be found that fast: the node participants, made
// after it, can announce at another period.
//
// What it rests on (Fast DDS 2.14, rmw_fastrtps for Jazzy): rmw_fastrtps
// makes each participant from DomainParticipantFactory's default participant
// QoS (get_default_participant_qos, with the XML profiles' default applied
// once, at the first load_profiles); set_default_participant_qos replaces it
// for every participant made afterwards, and changes none that exists. This
// library links the same libfastrtps the process already has loaded, so the
// factory is the process's one singleton. Called from one container thread
// while no participant is being made (cli.py: after the container's own
// Context, before the host makes any node's).

#include <cstdint>

#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/qos/DomainParticipantQos.hpp>
#include <fastrtps/xmlparser/XMLProfileManager.h>

using eprosima::fastdds::dds::DomainParticipantFactory;
using eprosima::fastdds::dds::DomainParticipantQos;
using eprosima::fastrtps::LibrarySettingsAttributes;
using eprosima::fastrtps::xmlparser::XMLProfileManager;

extern "C" {

// The default participant QoS's lease-announcement period and lease
// duration, in ns, as they are now: 0 on success, -1 if there is no factory.
__attribute__((visibility("default"))) int cg_dds_announcement(int64_t *period_ns,
                                                               int64_t *lease_ns)
{
    DomainParticipantFactory *factory = DomainParticipantFactory::get_instance();
    if (factory == nullptr) {
        return -1;
    }
    const auto &d = factory->get_default_participant_qos().wire_protocol().builtin.discovery_config;
    *period_ns = static_cast<int64_t>(d.leaseDuration_announcementperiod.seconds) * 1000000000 +
                 d.leaseDuration_announcementperiod.nanosec;
    *lease_ns =
        static_cast<int64_t>(d.leaseDuration.seconds) * 1000000000 + d.leaseDuration.nanosec;
    return 0;
}

// Participants made from now on re-announce every period_ns (and keep a
// lease of lease_ns, which must be longer). 0 on success, -1 if Fast DDS
// refused the QoS (its log says why).
__attribute__((visibility("default"))) int cg_dds_set_announcement(int64_t period_ns,
                                                                   int64_t lease_ns)
{
    DomainParticipantFactory *factory = DomainParticipantFactory::get_instance();
    if (factory == nullptr || period_ns <= 0 || lease_ns <= period_ns) {
        return -1;
    }
    factory->load_profiles(); // the XML default first, so that it cannot replace ours later
    DomainParticipantQos qos = factory->get_default_participant_qos();
    auto &d = qos.wire_protocol().builtin.discovery_config;
    d.leaseDuration_announcementperiod =
        eprosima::fastrtps::Duration_t(static_cast<int32_t>(period_ns / 1000000000),
                                       static_cast<uint32_t>(period_ns % 1000000000));
    d.leaseDuration = eprosima::fastrtps::Duration_t(static_cast<int32_t>(lease_ns / 1000000000),
                                                     static_cast<uint32_t>(lease_ns % 1000000000));
    return factory->set_default_participant_qos(qos) ==
                   eprosima::fastrtps::types::ReturnCode_t::RETCODE_OK
               ? 0
               : -1;
}

// Fast DDS's intraprocess delivery off for every match made from now on;
// what it was (0 off, 1 user data only, 2 full) in *was. Fast DDS reads
// the process-wide library settings each time a writer matches a reader
// of the same process (RTPSDomainImpl::should_intraprocess_between), so
// this holds for every node participant made after it, whatever the XML
// profile said (the profile was loaded with the container's participant).
__attribute__((visibility("default"))) int cg_dds_intraprocess_off(int *was)
{
    LibrarySettingsAttributes settings = XMLProfileManager::library_settings();
    *was = static_cast<int>(settings.intraprocess_delivery);
    settings.intraprocess_delivery = eprosima::fastrtps::INTRAPROCESS_OFF;
    XMLProfileManager::library_settings(settings);
    return 0;
}
}
