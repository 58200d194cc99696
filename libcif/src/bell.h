/*
 * bell.h - the event channel beside the image (the doorbell) [ours], host side.
 *
 * The same protocol as dpm/doorbell.py: the device listens on a Unix datagram
 * socket in the image's directory, the image's resolved path with ".bell" for
 * ".dpm" (a file system socket: the directory's permissions keep other users out,
 * docs/security.md); a host binds an automatic abstract name, rings the device
 * with one byte after writing DevFlags and waits for the device's rings.
 * A ring is only a hint: callers re-read the flags and poll every millisecond.
 */
#ifndef CIFEMU_BELL_H
#define CIFEMU_BELL_H

#include <sys/socket.h>
#include <sys/un.h>

typedef struct cifemu_bell {
  int fd;
  struct sockaddr_un device;
  socklen_t device_len;
  /* the device's last ring asked for a ring on HOSTACK: written by every thread that
     waits on the bell, read by DevGetMessage; atomic (__atomic_*), a hint either way */
  int device_wants_ack;
} cifemu_bell;

int cifemu_bell_open(cifemu_bell *bell, const char *image_path);
void cifemu_bell_close(cifemu_bell *bell);
void cifemu_bell_ring(cifemu_bell *bell);
/* Rings, and asks the device for a ring once its mailbox is free: the device rings for a
   message it took only when asked (DevPutMessage, before it sleeps on a full mailbox). */
void cifemu_bell_ring_want_mailbox(cifemu_bell *bell);
/* Waits up to timeout_ns for a ring; 1 when rung, 0 otherwise. */
int cifemu_bell_wait(cifemu_bell *bell, long long timeout_ns);

#endif
