// The EEPROM of the host tests: a RAM image starting blank (0xFF) like a new ATmega2560's.
#include <cstring>

#include "nvm_host.h"
#include "settings.h"

unsigned char nvm_image[4096];

void nvm_erase() { std::memset(nvm_image, 0xFF, sizeof(nvm_image)); }

void nvm_read(uint16_t addr, void *dst, uint16_t n) { std::memcpy(dst, nvm_image + addr, n); }
void nvm_write(uint16_t addr, const void *src, uint16_t n) { std::memcpy(nvm_image + addr, src, n); }
