/* rclglue: take messages from an rcl subscription together with the gid of
 * the DDS writer that sent each one, and read a publisher's own gid.
 *
 * rclpy's take gives no publisher gid, and an intra-process subscription
 * needs it to drop the DDS copy of a message it already got by reference
 * (container/intra/dds_reader.py).  Both sides must be the same 16 bytes:
 * with rmw_fastrtps, rmw_get_gid_for_publisher() and the message info's
 * publisher_gid are both the writer's GUID (12-byte prefix + 4-byte entity
 * id), so a byte comparison is exact.
 *
 * And finalize a service rclpy leaves unfinalized (cgr_service_fini), and
 * publish a ComponentEvent from a thread without the GIL: the clone core's
 * herald, which publishes a node's CRASHED event (cgr_event_publish).
 *
 * The pointers come from rclpy's handles (`handle.pointer`).  The caller
 * keeps the handle in use (`with handle:`) around every call, so rclpy can
 * not finalize the rcl object under us.
 *
 * Errors: rcl/rcutils keep one error state per thread.  Every failure path
 * copies it into the caller's buffer and resets it, so nothing is left set
 * for the next rcl call on this thread (rcutils complains, on stderr, when
 * an error is overwritten without having been reset). */
#include "rclglue.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cloneguard_interfaces/msg/detail/component_event__struct.h"

#include "rcl/error_handling.h"
#include "rmw/rmw.h"
#include "rmw/serialized_message.h"

/* CGR_GID_SIZE is what Python slices gids with; it must be rmw's size. */
_Static_assert(RMW_GID_STORAGE_SIZE == CGR_GID_SIZE, "rmw gid size is not 16 bytes");

/* Copy the thread's rcl error (with what we were doing) into err, reset it. */
static void take_error(const char *what, rcl_ret_t ret, char *err, size_t err_size)
{
    if (err != NULL && err_size > 0) {
        if (rcl_error_is_set()) {
            snprintf(err, err_size, "%s failed (rcl_ret %d): %s", what, (int)ret,
                     rcl_get_error_string().str);
        } else {
            snprintf(err, err_size, "%s failed (rcl_ret %d)", what, (int)ret);
        }
    }
    rcl_reset_error();
}

/* msg must be zeroed memory (ffi.new gives that) or a finalized message. */
int cgr_message_init(rcl_serialized_message_t *msg, size_t capacity, char *err, size_t err_size)
{
    rcutils_allocator_t allocator = rcutils_get_default_allocator();
    *msg = rmw_get_zero_initialized_serialized_message();
    rcutils_ret_t ret = rmw_serialized_message_init(msg, capacity, &allocator);
    if (ret != RCUTILS_RET_OK) {
        take_error("rmw_serialized_message_init", ret, err, err_size);
        return CGR_ERROR;
    }
    return 0;
}

/* Safe on a zeroed or already finalized message: fini of a message that was
 * never initialized would fail the allocator check, so skip it. */
void cgr_message_fini(rcl_serialized_message_t *msg)
{
    if (msg == NULL || msg->allocator.deallocate == NULL)
        return;
    if (rmw_serialized_message_fini(msg) != RCUTILS_RET_OK)
        rcl_reset_error();
    *msg = rmw_get_zero_initialized_serialized_message();
}

int cgr_publisher_gid(const rcl_publisher_t *publisher, uint8_t *gid_out, char *err,
                      size_t err_size)
{
    /* NULL with an error set if the publisher is not valid (finalized, or
     * its context shut down). */
    rmw_publisher_t *rmw_pub = rcl_publisher_get_rmw_handle(publisher);
    if (rmw_pub == NULL) {
        take_error("rcl_publisher_get_rmw_handle", RCL_RET_PUBLISHER_INVALID, err, err_size);
        return CGR_ERROR;
    }
    rmw_gid_t gid;
    rmw_ret_t ret = rmw_get_gid_for_publisher(rmw_pub, &gid);
    if (ret != RMW_RET_OK) {
        take_error("rmw_get_gid_for_publisher", ret, err, err_size);
        return CGR_ERROR;
    }
    memcpy(gid_out, gid.data, CGR_GID_SIZE);
    return 0;
}

int cgr_take_serialized(const rcl_subscription_t *subscription, rcl_serialized_message_t *msg,
                        uint8_t *gid_out, char *err, size_t err_size)
{
    rmw_message_info_t info = rmw_get_zero_initialized_message_info();
    /* The rmw grows msg->buffer (with msg's own allocator) when a message
     * does not fit, and sets buffer_length to the message's CDR size; the
     * capacity is kept for the next take. */
    rcl_ret_t ret = rcl_take_serialized_message(subscription, msg, &info, NULL);
    if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
        /* "Nothing to take" is not an error, but rcl may still have set the
         * error state on the way: do not leave it behind. */
        rcl_reset_error();
        return CGR_NOT_TAKEN;
    }
    if (ret != RCL_RET_OK) {
        take_error("rcl_take_serialized_message", ret, err, err_size);
        return CGR_ERROR;
    }
    memcpy(gid_out, info.publisher_gid.data, CGR_GID_SIZE);
    return CGR_TAKEN;
}

int cgr_node_init(rcl_node_t **out, const char *name, rcl_context_t *context, char *err,
                  size_t err_size)
{
    /* A node process's placeholder (container/isolated/spare.py): its
     * context's first node, so rmw makes the participant here, with no
     * Python thread state held: a Fast DDS lock a dead node left taken
     * then blocks only this process, not every Python thread with it. */
    rcl_node_t *node = malloc(sizeof *node);
    if (node == NULL) {
        snprintf(err, err_size, "out of memory");
        return CGR_ERROR;
    }
    *node = rcl_get_zero_initialized_node();
    rcl_node_options_t options = rcl_node_get_default_options();
    options.enable_rosout = false;
    rcl_ret_t ret = rcl_node_init(node, name, "/", context, &options);
    if (ret != RCL_RET_OK) {
        take_error("rcl_node_init", ret, err, err_size);
        free(node);
        return CGR_ERROR;
    }
    *out = node;
    return 0;
}

int cgr_node_fini(rcl_node_t *node, char *err, size_t err_size)
{
    rcl_ret_t ret = rcl_node_fini(node);
    free(node);
    if (ret != RCL_RET_OK) {
        take_error("rcl_node_fini", ret, err, err_size);
        return CGR_ERROR;
    }
    return 0;
}

int cgr_service_fini(rcl_service_t *service, rcl_node_t *node, char *err, size_t err_size)
{
    /* rclpy 7.1 never finalizes a node's ~/get_type_description service
     * (factory.py says why this is called); fini of one already finalized
     * is a no-op in rcl, so this stays right once rclpy does it itself. */
    rcl_ret_t ret = rcl_service_fini(service, node);
    if (ret != RCL_RET_OK) {
        take_error("rcl_service_fini", ret, err, err_size);
        return CGR_ERROR;
    }
    return 0;
}

/* The herald's event (rclglue.h).  The layout is rosidl's, generated from
 * ComponentEvent.msg: the message is defined there alone. */
void cgr_event_write_death(void *msg, int32_t exit_signal, int32_t exit_code, int quarantined,
                           const char *text)
{
    cloneguard_interfaces__msg__ComponentEvent *e = msg;
    e->exit_signal = exit_signal;
    e->exit_code = exit_code;
    e->allocator_quarantined = quarantined != 0;
    rosidl_runtime_c__String *s = &e->error_message;
    size_t n = s->capacity ? strnlen(text, s->capacity - 1) : 0; /* capacity counts the NUL */
    memcpy(s->data, text, n);
    s->data[n] = '\0';
    s->size = n;
}

int cgr_event_publish(const rcl_publisher_t *publisher, void *msg, char *err, size_t err_size)
{
    cloneguard_interfaces__msg__ComponentEvent *e = msg;
    struct timespec now;
    clock_gettime(CLOCK_REALTIME, &now);
    e->stamp.sec = (int32_t)now.tv_sec;
    e->stamp.nanosec = (uint32_t)now.tv_nsec;
    rcl_ret_t ret = rcl_publish(publisher, e, NULL);
    if (ret != RCL_RET_OK) {
        take_error("rcl_publish", ret, err, err_size);
        return CGR_ERROR;
    }
    return 0;
}
