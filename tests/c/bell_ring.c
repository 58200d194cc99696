/*
 * bell_ring.c - libcif's doorbell (libcif/src/bell.c) rings the socket the firmware binds.
 *
 * The firmware's doorbell is the file system socket board<N>.bell beside the image
 * (dpm/doorbell.py, docs/security.md), no longer an abstract name any user could take.
 * This program opens the host's side for an image path, prints the device address it
 * derived and rings it once. Built for x86-64 and, where gcc-multilib is there, for i386
 * (the legacy preload's size of sockaddr_un and socklen_t).
 *
 * Usage: bell_ring IMAGE; exit status 0 when the bell opened and rang, 2 when it refused
 * to open (errno's text on stderr).
 */
#include <errno.h>
#include <stdio.h>
#include <string.h>

#include "bell.h"

int main(int argc, char **argv) {
  cifemu_bell bell;
  if (argc != 2) {
    fprintf(stderr, "usage: bell_ring IMAGE\n");
    return 1;
  }
  if (cifemu_bell_open(&bell, argv[1]) != 0) {
    fprintf(stderr, "bell_ring: %s\n", strerror(errno));
    return 2;
  }
  printf("%s\n", bell.device.sun_path);
  cifemu_bell_ring(&bell);
  cifemu_bell_close(&bell);
  return 0;
}
