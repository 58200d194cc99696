/* bell.c - the doorbell [ours] (see bell.h). */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include "bell.h"

#include <errno.h>
#include <limits.h>
#include <poll.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define RING_WANT_ACK 0x02
#define RING_WANT_MAILBOX 0x03 /* dpm/doorbell.py _RING_WANT_MAILBOX */

int cifemu_bell_open(cifemu_bell *bell, const char *image_path) {
  static const char suffix[] = ".bell";
  char resolved[PATH_MAX];
  struct sockaddr_un self;
  size_t length;
  char *dot;

  memset(bell, 0, sizeof *bell);
  bell->fd = -1;
  bell->device_wants_ack = 1; /* nothing waits on a missed hint */
  if (realpath(image_path, resolved) == NULL) return -1;
  /* board<N>.dpm -> board<N>.bell, beside the image (dpm/image.py socket_path) */
  dot = strrchr(resolved, '.');
  if (dot == NULL || strchr(dot, '/') != NULL) dot = resolved + strlen(resolved);
  length = (size_t)(dot - resolved);
  if (length + sizeof suffix > sizeof bell->device.sun_path) {
    errno = ENAMETOOLONG;
    return -1;
  }
  bell->device.sun_family = AF_UNIX;
  memcpy(bell->device.sun_path, resolved, length);
  memcpy(bell->device.sun_path + length, suffix, sizeof suffix); /* with its NUL */
  bell->device_len =
      (socklen_t)(offsetof(struct sockaddr_un, sun_path) + length + sizeof suffix);
  bell->fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (bell->fd < 0) return -1;
  memset(&self, 0, sizeof self);
  self.sun_family = AF_UNIX;
  if (bind(bell->fd, (struct sockaddr *)&self, sizeof(sa_family_t)) != 0) { /* autobind */
    close(bell->fd);
    bell->fd = -1;
    return -1;
  }
  return 0;
}

void cifemu_bell_close(cifemu_bell *bell) {
  if (bell->fd >= 0) close(bell->fd);
  bell->fd = -1;
}

static void ring_with(cifemu_bell *bell, unsigned char ring) {
  /* A refused or full queue costs the device one poll interval, never correctness. */
  (void)sendto(bell->fd, &ring, 1, MSG_DONTWAIT | MSG_NOSIGNAL,
               (const struct sockaddr *)&bell->device, bell->device_len);
}

void cifemu_bell_ring(cifemu_bell *bell) { ring_with(bell, 0x01); }

void cifemu_bell_ring_want_mailbox(cifemu_bell *bell) { ring_with(bell, RING_WANT_MAILBOX); }

int cifemu_bell_wait(cifemu_bell *bell, long long timeout_ns) {
  struct pollfd pfd;
  unsigned char buf[16];
  int rung = 0;
  ssize_t got;
  pfd.fd = bell->fd;
  pfd.events = POLLIN;
  if (timeout_ns < 0) timeout_ns = 0;
  /* whole milliseconds, rounded up: a wait never ends before its time */
  if (poll(&pfd, 1, (int)((timeout_ns + 999999) / 1000000)) <= 0) return 0;
  while ((got = recv(bell->fd, buf, sizeof buf, MSG_DONTWAIT)) > 0) {
    rung = 1;
    __atomic_store_n(&bell->device_wants_ack, buf[0] == RING_WANT_ACK, __ATOMIC_RELAXED);
  }
  return rung;
}
