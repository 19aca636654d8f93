/* rclglue: the rcl calls rclpy does not give us (see rclglue.c).
 *
 * Between the cdef markers: the cdef of _build_rclglue.py's module
 * (scripts/cdef.py). */
#ifndef CLONEGUARD_INTRA_RCLGLUE_H
#define CLONEGUARD_INTRA_RCLGLUE_H

#include <stddef.h>
#include <stdint.h>

#include "rcl/node.h"
#include "rcl/publisher.h"
#include "rcl/service.h"
#include "rcl/subscription.h"

/* cdef: begin */
/* Bytes of a DDS endpoint's gid as rmw gives it (rmw_gid_t.data). */
#define CGR_GID_SIZE 16

/* cgr_take_serialized() results. */
#define CGR_TAKEN 1
#define CGR_NOT_TAKEN 0
#define CGR_ERROR (-1)

/* Room callers give for an error text: longer texts are cut. */
#define CGR_ERR_SIZE 512

int cgr_message_init(rcl_serialized_message_t *msg, size_t capacity, char *err, size_t err_size);
void cgr_message_fini(rcl_serialized_message_t *msg);

int cgr_publisher_gid(const rcl_publisher_t *publisher, uint8_t *gid_out, char *err,
                      size_t err_size);

int cgr_take_serialized(const rcl_subscription_t *subscription, rcl_serialized_message_t *msg,
                        uint8_t *gid_out, char *err, size_t err_size);

/* rcl_service_fini(service, node): 0, or CGR_ERROR with the text in err. */
int cgr_service_fini(rcl_service_t *service, rcl_node_t *node, char *err, size_t err_size);

/* A bare rcl node (no rosout, no client library around it) on context, in
   *out (heap); 0, or CGR_ERROR with the text in err.  cgr_node_fini
   finalizes and frees it.  Called without the GIL (cffi releases it). */
int cgr_node_init(rcl_node_t **out, const char *name, rcl_context_t *context, char *err,
                  size_t err_size);
int cgr_node_fini(rcl_node_t *node, char *err, size_t err_size);

/* A node's CRASHED event as the clone core's herald sends it
   (isolated/clonecore/herald.c): a cloneguard_interfaces/msg/ComponentEvent C message
   Python made from the event it would publish itself.  What only the death
   tells is written into it on the monitor thread, without allocating:
   error_message's buffer was made big enough when Python made the message
   (a longer text is cut to it). */
void cgr_event_write_death(void *msg, int32_t exit_signal, int32_t exit_code, int quarantined,
                           const char *text);
/* Stamp msg with the time now and publish it on publisher: 0, or CGR_ERROR
   with the text in err.  For a thread without the GIL (the herald's). */
int cgr_event_publish(const rcl_publisher_t *publisher, void *msg, char *err, size_t err_size);
/* cdef: end */

#endif
